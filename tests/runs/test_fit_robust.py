"""``reeb fit`` as a careless or hostile user runs it: outputs checked before any work, a lock,
files renamed into place, a config that reads from any folder; label files with impossible
boxes refused in one line naming the file and the line, by every command."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import torch

from reeb_torch.datasets.kitti import KittiDataset, box_problem, read_kitti_labels

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples" / "data"
LINE = "Car 0.00 0 -1.58 {} 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"


def _folder(root: Path, extra_label: str = "") -> Path:
    """A KITTI-format folder of the two bundled frames (``extra_label`` appended to the second's labels)."""
    for sub in ("images", "labels", "calib"):
        (root / sub).mkdir(parents=True)
    for n, stem in enumerate(("000001", "000008")):
        shutil.copy(EXAMPLES / f"kitti_{stem}.png", root / "images" / f"{stem}.png")
        shutil.copy(EXAMPLES / f"kitti_{stem}_calib.txt", root / "calib" / f"{stem}.txt")
        text = (EXAMPLES / f"kitti_{stem}.txt").read_text()
        (root / "labels" / f"{stem}.txt").write_text(text + (extra_label if n else ""))
    return root


def _fit(args, cwd: Path, monkeypatch):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    monkeypatch.chdir(cwd)
    res = CliRunner().invoke(main, ["fit", *map(str, args)])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res


def _one_line(res, code: int) -> str:
    assert res.exit_code == code, res.output
    lines = [ln for ln in res.output.strip().splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    return lines[0]


# -- outputs checked before any work (rows 5, 9) -------------------------------------------

@pytest.mark.slow
def test_the_weights_and_their_config_are_never_one_file(tmp_path):
    _folder(tmp_path / "d")
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", "d", "--folds", "2", "-q", "-o",
                        "mine.json"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "the same file" in lines[0] and "-o mine.safetensors" in lines[0], r.stderr
    assert not (tmp_path / "mine.json").exists()


@pytest.mark.parametrize("out,message", [
    ("", "-o/--out is empty"),
    ("d/images/000001.png/w.safetensors", "d/images/000001.png is a file, not a folder"),
    ("/proc/m.safetensors", "cannot write to the folder /proc"),
    ("w.JSON", "the same file"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, monkeypatch, out, message):
    from reeb_torch.ranker import frames as F

    _folder(tmp_path / "d")
    monkeypatch.setattr(F, "load_fit_frames", lambda *a, **k: pytest.fail("the frames were read"))
    line = _one_line(_fit(["d", "--folds", "2", "-q", "-o", out], tmp_path, monkeypatch), 2)
    assert message in line


def test_a_second_fit_on_the_same_output_exits_2(tmp_path, monkeypatch):
    from reeb_torch.ranker import frames as F
    from reeb_torch.runs.output_lock import lock_output

    _folder(tmp_path / "d")
    (tmp_path / "w.safetensors").write_bytes(b"old")
    monkeypatch.setattr(F, "load_fit_frames", lambda *a, **k: pytest.fail("the frames were read"))
    with lock_output(tmp_path / "w.safetensors"):  # the first fit, still running
        line = _one_line(_fit(["d", "--folds", "2", "-q", "-o", "w.safetensors", "--overwrite"], tmp_path, monkeypatch), 2)
    assert "another reeb run" in line and f"pid {os.getpid()}" in line
    assert (tmp_path / "w.safetensors").read_bytes() == b"old"


def test_nan_weights_to_start_from_are_refused_before_the_frames_are_read(tmp_path, monkeypatch):
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import shipped_path

    _folder(tmp_path / "d")
    tensors = load_file(str(shipped_path("kitti")))
    with safe_open(str(shipped_path("kitti")), framework="pt") as f:
        meta = f.metadata()
    tensors["members.0.0.weight"][:] = float("nan")
    save_file(tensors, str(tmp_path / "nan.safetensors"), metadata=meta)
    monkeypatch.setattr(F, "load_fit_frames", lambda *a, **k: pytest.fail("the frames were read"))
    line = _one_line(_fit(["d", "--folds", "2", "-q", "--init", "nan.safetensors", "-o", "out.safetensors"],
                          tmp_path, monkeypatch), 2)
    assert "nan.safetensors" in line and "'members.0.0.weight'" in line and "not finite" in line
    assert not (tmp_path / "out.safetensors").exists()


# -- what a fit writes (rows 2, 4, 10) ------------------------------------------------------

def _model():
    from reeb_torch.ranker import BoxRanker, load_ranker

    return BoxRanker(load_ranker("kitti").feature_names, (8,), prefilter=(4,))


def test_a_full_disk_leaves_the_old_weights_and_config(tmp_path, monkeypatch):
    from reeb_torch import ReebConfig
    from reeb_torch.ranker import weights as W
    from reeb_torch.runs.common import Failure
    from reeb_torch.runs.fit import FitOutputs

    (tmp_path / "w.safetensors").write_bytes(b"old weights")
    (tmp_path / "w.json").write_text("old config")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(W.os, "fsync", full)
    with FitOutputs(tmp_path / "w.safetensors", overwrite=True) as outputs, pytest.raises(Failure) as e:
        outputs.write(_model(), {}, ReebConfig())
    assert e.value.exit_code == 1 and "No space left" in e.value.message and "unchanged" in e.value.message
    assert (tmp_path / "w.safetensors").read_bytes() == b"old weights"
    assert (tmp_path / "w.json").read_text() == "old config"
    assert sorted(os.listdir(tmp_path)) == ["w.json", "w.safetensors"]  # no temporary file, lock or scratch


def test_a_fit_that_gave_nan_weights_writes_nothing(tmp_path):
    from reeb_torch import ReebConfig
    from reeb_torch.runs.common import Failure
    from reeb_torch.runs.fit import FitOutputs

    model = _model()
    with torch.no_grad():
        model.mean[3] = float("nan")
    with FitOutputs(tmp_path / "w.safetensors") as outputs, pytest.raises(Failure) as e:
        outputs.write(model, {}, ReebConfig())
    assert "not written" in e.value.message and "tensor 'mean'" in e.value.message
    assert os.listdir(tmp_path) == []


def test_the_config_names_the_weights_from_its_own_folder(tmp_path, monkeypatch):
    from reeb_torch import ReebConfig
    from reeb_torch.runs.common import build_config
    from reeb_torch.runs.fit import FitOutputs

    monkeypatch.chdir(tmp_path)
    with FitOutputs("conc/same.safetensors") as outputs:
        outputs.write(_model(), {}, ReebConfig().replace(horizon=0.48))
        assert outputs.hint().endswith("(reeb propose --config conc/same.json)")
    assert json.loads((tmp_path / "conc" / "same.json").read_text()) == {"horizon": 0.48,
                                                                         "ranker": "same.safetensors"}
    other = tmp_path / "other"
    other.mkdir()
    monkeypatch.chdir(other)
    cfg = build_config("default", "../conc/same.json", (), None)
    assert Path(cfg.ranker).resolve() == (tmp_path / "conc" / "same.safetensors").resolve()
    monkeypatch.chdir(tmp_path)  # a config written with a path from the folder it ran in still reads
    (tmp_path / "conc" / "old.json").write_text(json.dumps({"ranker": "conc/same.safetensors"}))
    assert build_config("default", "conc/old.json", (), None).ranker == "conc/same.safetensors"
    with FitOutputs("a b/kitti") as outputs:  # a file named as a shipped model is named as a file
        outputs.write(_model(), {}, ReebConfig())
        assert outputs.hint().endswith("(reeb propose --config 'a b/kitti.json')")
    assert json.loads((tmp_path / "a b" / "kitti.json").read_text())["ranker"] == "./kitti"


def test_the_scratch_folder_is_beside_the_output_and_a_killed_fits_is_removed(tmp_path):
    from reeb_torch.runs.fit import FitOutputs

    before = tempfile.gettempdir()
    stale = tmp_path / ".w.safetensors.fit"
    stale.mkdir()
    (stale / "left-by-a-kill").write_text("x")
    (tmp_path / ".w.safetensors.abcd1234.tmp").write_bytes(b"half a file")
    with FitOutputs(tmp_path / "w.safetensors") as outputs:
        assert outputs.scratch == stale and stale.is_dir() and not (stale / "left-by-a-kill").exists()
        assert tempfile.gettempdir() == before  # the fit's folds go to outputs.scratch, named, not the process's
    assert os.listdir(tmp_path) == []


# -- labels (row 6) -------------------------------------------------------------------------

@pytest.mark.parametrize("box,problem", [
    ("600 180 500 200", "inverted or has no area"),
    ("-50 -40 -10 -5", "negative coordinates"),
    ("1300 100 1400 200", "leaves the 1242x375 image"),
    ("600 180 600 200", "inverted or has no area"),
    ("nan 180 620 200", "not a finite number"),
])
def test_an_impossible_label_box_is_an_error_naming_the_file_and_the_line(tmp_path, box, problem):
    d = _folder(tmp_path / "d", LINE.format(box))
    line = len((d / "labels" / "000008.txt").read_text().splitlines())
    with pytest.raises(ValueError, match=f"000008.txt:{line}: impossible box .*{problem}"):
        KittiDataset(d).load_target(1)
    with pytest.raises(ValueError, match=f"000008.txt:{line}: impossible box .*{problem}"):
        KittiDataset(d)[1]


def test_label_boxes_inside_the_image_are_kept():
    assert box_problem((0.0, 0.0, 1241.0, 374.0), (1242, 375)) is None
    assert box_problem((-0.5, 0.0, 1242.4, 375.0), (1242, 375)) is None  # rounding in converted labels
    assert box_problem((-0.5, 0.0, 1250.0, 375.0)) is None  # without the size, no upper bound
    assert len(read_kitti_labels(EXAMPLES / "kitti_000001.txt", image_size=(1242, 375))) > 0


@pytest.mark.parametrize("command", ["fit", "eval", "calibrate"])
def test_every_command_refuses_impossible_label_boxes_in_one_line(tmp_path, monkeypatch, command):
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    _folder(tmp_path / "d", LINE.format("600 180 500 200"))
    args = {"fit": ["fit", "d", "--folds", "2", "-q", "-o", "w.safetensors"],
            "eval": ["eval", "d", "--methods", "reeb-training-free", "--out", "t3"],
            "calibrate": ["calibrate", "d", "-o", "cam.json"]}[command]
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and "Traceback" not in res.stderr, (res.output, res.stderr)
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    errors = [ln for ln in res.stderr.splitlines() if "impossible box" in ln]
    assert len(errors) == 1 and "d/labels/000008.txt:" in errors[0] and "inverted" in errors[0], res.stderr
    assert not (tmp_path / "w.safetensors").exists() and not (tmp_path / "cam.json").exists()


# -- a whole fit, written where a second folder reads it (rows 4, 10, 11 together) ------------

@pytest.mark.slow
@pytest.mark.kitti
def test_a_fit_writes_files_that_read_from_any_folder_and_leaves_nothing_else(kitti_dir, tmp_path):
    d = tmp_path / "d"
    for sub in ("images", "labels", "calib"):
        (d / sub).mkdir(parents=True)
        for stem in ("000000", "000001"):
            src = next((kitti_dir / sub).glob(f"{stem}.*"))
            shutil.copy(src, d / sub / src.name)
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "fit", "d", "--folds", "2", "--epochs", "1",
                        "-q", "-o", "conc dir/same.safetensors"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1].endswith("(reeb propose --config 'conc dir/same.json')")
    assert sorted(os.listdir(tmp_path / "conc dir")) == ["same.json", "same.safetensors"]  # no lock, scratch
    other = tmp_path / "other"
    other.mkdir()
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "propose", str(EXAMPLES / "kitti_000001.png"),
                        "--config", "../conc dir/same.json", "-o", "o.jsonl", "--device", "cpu", "-q"], cwd=other,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    row = json.loads((other / "o.jsonl").read_text().splitlines()[0])
    assert row["status"] == "ok" and len(row["scores"]) > 0
