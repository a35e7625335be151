"""reeb propose --engine ray (reeb_torch.runs.distributed) against the single-process path.

One local Ray instance (2 CPUs, no dashboard) serves the whole module; the tests skip when
Ray is not installed. The reference is the single-process ``reeb propose`` writing Parquet
(the same float32 columns), compared row by row.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

ray = pytest.importorskip("ray")
pytest.importorskip("ray.data")
pytest.importorskip("pyarrow")

from reeb_torch.runs.cli import main  # noqa: E402
from reeb_torch.runs.distributed import actor_cpus, torch_threads  # noqa: E402
from reeb_torch.runs.output_files import read_result_dir, result_files  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples" / "data"


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             logging_level="ERROR", configure_logging=True)
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def small_images(tmp_path_factory) -> Path:
    """Four generated images of other sizes and pixel types, cut from the bundled frame."""
    import cv2

    d = tmp_path_factory.mktemp("small")
    bgr = cv2.imread(str(EXAMPLES / "kitti_000001.png"), cv2.IMREAD_COLOR)
    crop = bgr[120:375, 300:700]                                       # 400×255 RGB
    cv2.imwrite(str(d / "a_crop.png"), crop)
    cv2.imwrite(str(d / "b_small.png"), cv2.resize(bgr, (320, 97)))    # 320×97
    grey16 = (cv2.cvtColor(bgr[100:340, 600:920], cv2.COLOR_BGR2GRAY).astype(np.uint16) * 257)
    cv2.imwrite(str(d / "c_grey16.png"), grey16)                      # 320×240, 16-bit grey
    rgba = cv2.cvtColor(bgr[150:330, 200:480], cv2.COLOR_BGR2BGRA)
    cv2.imwrite(str(d / "d_rgba.png"), rgba)                          # 280×180, RGBA
    return d


def _run(*args):
    return CliRunner().invoke(main, ["propose", *map(str, args)], catch_exceptions=False)


def _by_image(rows):
    out = {}
    for r in rows:
        assert r["image"] not in out, f"{r['image']} has two rows"
        out[r["image"]] = r
    return out


def _local_rows(tmp_path, *paths):
    import pyarrow.parquet as pq

    ref = tmp_path / "local.parquet"
    res = _run(*paths, "-o", ref, "-q", "-j", "0")
    assert res.exit_code in (0, 1), res.output
    return _by_image(pq.read_table(ref).to_pylist())


def test_actor_sizing_leaves_room_for_read_and_write_tasks():
    assert actor_cpus(2, 1) == 1.0 and actor_cpus(2, 2) == 0.5
    assert actor_cpus(16, 3) == 5.0
    assert actor_cpus(1, 1) == 0.5
    assert actor_cpus(2, 8) == 0.25          # floor: a quarter CPU
    assert actor_cpus(2, 2, 0.75) == 0.75    # given: used as is
    assert torch_threads(0.5) == 1 and torch_threads(3.0) == 3
    with pytest.raises(ValueError):
        actor_cpus(2, 0)


@pytest.mark.slow
def test_ray_rows_equal_single_process(local_ray, small_images, tmp_path, monkeypatch):
    # relative paths (from the working folder) are written as given
    monkeypatch.chdir(small_images.parent)
    rel = Path(small_images.name)
    inputs = [EXAMPLES / "kitti_000001.png", EXAMPLES / "kitti_000008.png", rel]
    ref = _local_rows(tmp_path, *inputs)
    out = tmp_path / "ray.parquet"
    res = _run(*inputs, "--engine", "ray", "--actors", "2", "-o", out,
               "--summary-json", tmp_path / "s.json")
    assert res.exit_code == 0, res.output
    assert "6 images: 6 ok, 0 failed" in res.output and "ms/img" in res.output
    got = _by_image(read_result_dir(out))
    assert set(got) == set(ref)
    assert str(rel / "a_crop.png") in got          # relative, as given
    for image, r in ref.items():
        g = got[image]
        assert g.keys() == r.keys()
        assert g == r, f"{image}: rows differ"
        assert r["status"] == "ok" and len(r["boxes"]) > 0
    assert got[str(rel / "c_grey16.png")]["width"] == 320


@pytest.mark.slow
def test_bad_files_give_error_rows_and_exit_1(local_ray, small_images, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 64)
    (bad / "notes.png").write_text("this is text, not an image\n")
    good = sorted(small_images.glob("*.png"))[:2]
    out = tmp_path / "ray.parquet"
    res = _run(*good, bad / "corrupt.png", bad / "notes.png", "--engine", "ray", "-o", out, "-q")
    assert res.exit_code == 1, res.output
    assert "2 ok, 2 failed" in res.output
    rows = read_result_dir(out)
    got = _by_image(rows)                            # every image exactly once
    assert len(rows) == 4
    for g in good:
        assert got[str(g)]["status"] == "ok"
    assert got[str(bad / "corrupt.png")]["status"].startswith(f"error: {bad / 'corrupt.png'}")
    assert got[str(bad / "notes.png")]["status"].startswith("error: ")
    assert got[str(bad / "notes.png")]["boxes"] == []

    # export skips the failed images, names them, and round-trips
    pkl = tmp_path / "p.pkl"
    res = CliRunner().invoke(main, ["export", str(out), "-o", str(pkl)])
    assert res.exit_code == 0, res.output
    assert "2 failed images left out" in res.output
    d = pickle.loads(pkl.read_bytes())
    assert sorted(d["ids"]) == sorted(g.stem for g in good)
    for i, b in zip(d["ids"], d["boxes"]):
        row = got[str(small_images / f"{i}.png")]
        np.testing.assert_array_equal(b, np.asarray(row["boxes"], np.float32))

    # the text file is fixed: --resume redoes it and drops its old error row
    (bad / "notes.png").write_bytes((small_images / "b_small.png").read_bytes())
    res = _run(*good, bad / "corrupt.png", bad / "notes.png", "--engine", "ray", "-o", out, "-q",
               "--resume")
    assert res.exit_code == 1, res.output          # corrupt.png still fails
    got = _by_image(read_result_dir(out))          # still one row per image
    assert len(got) == 4 and got[str(bad / "notes.png")]["status"] == "ok"
    assert got[str(bad / "corrupt.png")]["status"].startswith("error: ")


@pytest.mark.slow
def test_resume_adds_only_the_missing_images(local_ray, small_images, tmp_path):
    images = sorted(small_images.glob("*.png"))
    out = tmp_path / "ray.parquet"
    res = _run(*images[:2], "--engine", "ray", "-o", out, "-q")
    assert res.exit_code == 0, res.output
    first = set(result_files(out))
    res = _run(*images, "--engine", "ray", "-o", out)
    assert res.exit_code == 2 and "--resume" in res.output   # no silent overwrite
    res = _run(*images, "--engine", "ray", "-o", out, "--resume")
    assert res.exit_code == 0, res.output
    assert "2 images: 2 ok" in res.output and "2 kept from before" in res.output
    new = set(result_files(out)) - first
    new_rows = [r for f in new for r in __import__("pyarrow.parquet").parquet.read_table(f).to_pylist()]
    assert sorted(r["image"] for r in new_rows) == sorted(map(str, images[2:]))
    rows = read_result_dir(out)
    assert sorted(r["image"] for r in rows) == sorted(map(str, images))
    res = _run(*images, "--engine", "ray", "-o", out, "--resume")
    assert res.exit_code == 0 and "Nothing to do" in res.output


def test_usage_errors_before_any_work(tmp_path):
    res = _run(EXAMPLES, "--engine", "ray", "-o", tmp_path / "x.jsonl")
    assert res.exit_code == 2 and "folder of Parquet files" in res.output
    res = _run(EXAMPLES, "--engine", "ray")
    assert res.exit_code == 2 and "--out" in res.output


@pytest.mark.slow
def test_api_takes_an_existing_dataset(local_ray, small_images):
    from reeb_torch import ReebConfig
    from reeb_torch.runs.output_files import ParquetWriter
    from reeb_torch.runs.distributed import propose_dataset

    path = str(small_images / "b_small.png")
    ds = ray.data.from_items([{"image": path}, {"image": str(small_images / "missing.png")}])
    rows = propose_dataset(ds, ReebConfig(), actors=1).take_all()   # default sizing: finishes
    got = _by_image(rows)
    assert set(got[path]) == set(ParquetWriter.schema().names)
    assert got[path]["status"] == "ok" and (got[path]["width"], got[path]["height"]) == (320, 97)
    assert got[str(small_images / "missing.png")]["status"].startswith("error: ")


@pytest.mark.slow
def test_non_utf8_name_and_quiet_ray_log(tmp_path):
    """A file name that is not UTF-8 gets an ``ok`` row in the escaped ``\\xNN`` form and
    ``--resume`` matches it; under ``-q`` none of Ray's INFO / WARNING lines reach stderr.
    A subprocess, so that this run starts Ray itself (as a user's run does)."""
    import os
    import re
    import shutil
    import subprocess
    import sys

    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(EXAMPLES / "kitti_000001.png", d / "a.png")
    shutil.copy(EXAMPLES / "kitti_000001.png", os.path.join(os.fsencode(d), b"x\xff.png"))
    args = ["propose", "d", "--engine", "ray", "--actors", "1", "-o", "o.parquet",
            "--top-k", "100", "--device", "cpu"]
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", *args, "-q"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    ray_lines = [ln for ln in r.stderr.splitlines()
                 if re.search(r"\b(INFO|WARNING|WARN)\b", ln) or "[Dataset]" in ln]
    assert not ray_lines, "\n".join(ray_lines)
    rows = read_result_dir(tmp_path / "o.parquet")
    assert len(rows) == 2 and all(row["status"] == "ok" for row in rows), rows
    assert {row["image"] for row in rows} == {"d/a.png", "d/x\\xff.png"}
    assert {row["resolved"] for row in rows} == {f"{d}/a.png", f"{d}/x\\xff.png"}
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", *args, "--resume"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0 and "Nothing to do" in r.stderr, r.stderr


def test_input_table_holds_a_non_utf8_name_as_plain_columns(local_ray, tmp_path):
    """The input dataset's columns are Arrow string / binary, not Ray's pickled-object
    fallback (which logs a WARNING and which Ray can turn off); ``open`` keeps the bytes."""
    import os

    import pyarrow as pa

    from reeb_torch.runs.distributed import paths_dataset

    name = os.path.join(os.fsencode(tmp_path), b"x\xff.png")
    ds = paths_dataset([os.fsdecode(name)])
    schema = ds.schema()
    types = dict(zip(schema.names, schema.types))
    assert types["image"] == pa.string() and types["open"] == pa.binary(), types
    (row,) = ds.take_all()
    assert row["image"] == f"{tmp_path}/x\\xff.png" and row["open"] == name
