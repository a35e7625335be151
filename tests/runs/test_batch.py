"""``reeb propose`` and its batch output under stress: concurrent writers, resume
from other folders, stale temporary files, row order, ``--set`` booleans, the row schema.

Subprocess tests drive the command as a user would; small 160×48 images and --top-k 100
keep them fast.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import click
import cv2
import numpy as np
import pytest

from tests.runs.test_cli import FAST, _start, _wait_for_rows, good_folder, no_temp_files, read_jsonl, reeb, small_frame

KITTI_CLASSES = ("Car", "Pedestrian", "Cyclist", "Truck")
ROW_FIELDS = {"format_version", "image", "resolved", "width", "height", "boxes", "scores",
              "labels", "status", "config"}


# -- concurrent writers ------------------------------------------------------------------------

@pytest.mark.slow
def test_second_writer_fails_at_once_and_loses_nothing(tmp_path):
    n = 300  # enough work that the other runs start while the first one is writing
    good_folder(tmp_path / "A", n)
    good_folder(tmp_path / "B", 2)
    first = _start(["propose", "A", "-o", "cc.jsonl", "-b", "1", *FAST], tmp_path)
    _wait_for_rows(tmp_path, "cc.jsonl", first)
    # the first run is paused mid-run (SIGSTOP; it still holds the output) while the others
    # start, however fast it would otherwise finish
    first.send_signal(signal.SIGSTOP)
    try:
        others = [_start(["propose", "B", "-o", "cc.jsonl", *extra, *FAST], tmp_path)
                  for extra in ([], ["--resume"])]
        for other in others:
            _, err = other.communicate(timeout=120)
            assert other.returncode == 2, err
            assert " ok, " not in err  # failed before any work, without waiting
            assert "another reeb run" in err and f"pid {first.pid}" in err, err
        assert first.poll() is None, "the first run ended too early for this test"
    finally:
        first.send_signal(signal.SIGCONT)
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    rows = read_jsonl(tmp_path / "cc.jsonl")
    assert len(rows) == n and all(r["image"].startswith("A") for r in rows)
    assert not (tmp_path / ".cc.jsonl.reeb-lock").exists() and no_temp_files(tmp_path)
    # after the first one, the second runs
    reeb("propose", "B", "-o", "cc.jsonl", "--resume", *FAST, cwd=tmp_path, check_rc=0)
    assert len(read_jsonl(tmp_path / "cc.jsonl")) == n + 2


@pytest.mark.slow
def test_a_run_on_a_locked_output_fails_before_any_work(tmp_path):
    from reeb_torch.runs.output_lock import lock_output

    good_folder(tmp_path / "B", 1)
    with lock_output(tmp_path / "cc.jsonl"):  # this test process plays the first run
        for extra in ([], ["--resume"], ["--overwrite"]):
            r = reeb("propose", "B", "-o", "cc.jsonl", *extra, *FAST, cwd=tmp_path, check_rc=2)
            assert f"another reeb run (pid {os.getpid()})" in r.stderr, r.stderr
            assert sorted(p.name for p in tmp_path.iterdir()) == [".cc.jsonl.reeb-lock", "B"]


def test_lock_of_a_dead_run_is_taken_over(tmp_path):
    from reeb_torch.runs.output_lock import OutputBusyError, lock_output

    out = tmp_path / "o.jsonl"
    (tmp_path / ".o.jsonl.reeb-lock").write_text("999999\n")  # left by a killed run: not locked
    with lock_output(out):
        assert (tmp_path / ".o.jsonl.reeb-lock").read_text().strip() == str(os.getpid())
        code = ("import sys; from reeb_torch.runs.output_lock import lock_output, OutputBusyError\n"
                f"try:\n    lock_output({str(out)!r})\nexcept OutputBusyError as e:\n"
                "    print(e); sys.exit(3)\n")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert r.returncode == 3 and str(os.getpid()) in r.stdout
    assert not (tmp_path / ".o.jsonl.reeb-lock").exists()
    assert issubclass(OutputBusyError, OSError)


# -- resume matches the resolved file ----------------------------------------------------------

@pytest.mark.slow
def test_resume_from_another_folder_symlink_and_absolute_path(tmp_path):
    paths = good_folder(tmp_path / "set", 5)
    names = [p.name for p in paths]
    reeb("propose", *[f"set/{n}" for n in names[:3]], "-o", "cwd.jsonl", *FAST, cwd=tmp_path,
         check_rc=0)
    r = reeb("propose", *names[:4], "-o", "../cwd.jsonl", "--resume", *FAST, cwd=tmp_path / "set",
             check_rc=0)
    assert "1 to do" in r.stderr, r.stderr
    rows = read_jsonl(tmp_path / "cwd.jsonl")
    assert [r["image"] for r in rows] == [f"set/{n}" for n in names[:3]] + [names[3]]  # as given
    for row in rows:
        assert row["resolved"] == os.path.realpath(tmp_path / "set" / Path(row["image"]).name)
    # through a symlinked folder, and by absolute path: nothing to do
    (tmp_path / "link").symlink_to(tmp_path / "set")
    r = reeb("propose", *[f"link/{n}" for n in names[:4]], "-o", "cwd.jsonl", "--resume", *FAST,
             cwd=tmp_path, check_rc=0)
    assert "Nothing to do" in r.stderr
    r = reeb("propose", *[str(p) for p in paths[:4]], "-o", str(tmp_path / "cwd.jsonl"), "--resume",
             *FAST, cwd="/", check_rc=0)
    assert "Nothing to do" in r.stderr
    # duplicate rows (a hand-merged file) are dropped on resume
    with open(tmp_path / "cwd.jsonl", "a") as f:
        f.write(json.dumps(rows[0]) + "\n")
    reeb("propose", "link", "-o", "cwd.jsonl", "--resume", *FAST, cwd=tmp_path, check_rc=0)
    rows = read_jsonl(tmp_path / "cwd.jsonl")
    assert sorted(r["resolved"] for r in rows) == sorted(os.path.realpath(p) for p in paths)


# -- --set booleans, config errors -------------------------------------------------------------

@pytest.mark.parametrize("word, value", [("true", True), ("False", False), ("yes", True),
                                         ("no", False), ("on", True), ("OFF", False),
                                         ("1", True), ("0", False), ('"false"', False)])
def test_set_parses_boolean_words(word, value):
    from reeb_torch.runs.common import build_config

    assert build_config("default", None, [f"use_regions={word}"], None).use_regions is value
    assert build_config("training-free", None, [f"thin_edges={word}"], None).thin_edges is value


@pytest.mark.parametrize("word", ["maybe", "2", "", "none", "[]", "offf"])
def test_set_rejects_other_boolean_words(word):
    from reeb_torch.runs.common import build_config

    with pytest.raises(click.ClickException) as info:
        build_config("default", None, [f"use_regions={word}"], None)
    assert info.value.exit_code == 2 and "use_regions" in info.value.format_message()


@pytest.mark.parametrize("field", ["shadow_score", "vegetation_score", "location_score", "road_score"])
def test_set_keeps_the_word_none_of_a_choice_field(field):
    # 'none' is one of these fields' words (the term off), not JSON null
    from reeb_torch.runs.common import build_config

    assert getattr(build_config("default", None, [f"{field}=none"], None), field) == "none"
    assert getattr(build_config("default", None, [f"{field}= none "], None), field) == "none"


def test_set_takes_the_ranker_as_written():
    # a free-text field: 'none' is the training-free ranking's word, a path stays a path
    from reeb_torch.runs.common import build_config

    assert build_config("default", None, ["ranker=none"], None).ranker == "none"
    assert build_config("default", None, ["ranker= none "], None).ranker == "none"
    assert build_config("default", None, ['ranker="kitti"'], None).ranker == "kitti"
    assert build_config("training-free", None, ["ranker=kitti"], None).ranker == "kitti"
    assert build_config("default", None, ["ranker=runs/mine.safetensors"], None).ranker == "runs/mine.safetensors"
    assert build_config("default", None, ["ranker=1"], None).ranker == "1"  # a file named 1, not the number
    with pytest.raises(click.BadParameter, match="ranker"):
        build_config("default", None, ["ranker= "], None)


def test_set_takes_every_word_of_every_choice_field():
    # each Literal field of ReebConfig, each of its words, as --set writes it
    import dataclasses
    import typing

    from reeb_torch.runs.common import build_config
    from reeb_torch.config import ReebConfig

    hints = typing.get_type_hints(ReebConfig)
    pairs = [(f.name, w) for f in dataclasses.fields(ReebConfig) if typing.get_origin(hints[f.name]) is typing.Literal
             for w in typing.get_args(hints[f.name])]
    assert len(pairs) >= 15
    for name, word in pairs:
        cfg = build_config("training-free", None, [f"{name}={word}"], None)
        assert getattr(cfg, name) == word, (name, word)


def test_set_still_reads_none_as_null_where_none_is_not_a_word():
    from reeb_torch.runs.common import build_config

    cfg = build_config("default", None, ["ground_band=none", "group_cell=null", "window_geometry=grid"], None)
    assert cfg.ground_band is None and cfg.group_cell is None and cfg.window_geometry == "grid"
    with pytest.raises(click.ClickException) as info:  # a word that is not a choice still fails
        build_config("default", None, ["shadow_score=None"], None)
    assert "shadow_score" in info.value.format_message()


def test_config_errors_are_usage_errors_before_any_work(tmp_path):
    good_folder(tmp_path / "imgs", 1)
    for bad in ("use_regions=maybe", "top_k=0", "no_such_field=1"):
        r = reeb("propose", "imgs", "-o", "o.jsonl", "--set", bad, "--device", "cpu", cwd=tmp_path)
        assert r.returncode == 2, (bad, r.stderr)
        assert bad.split("=")[0] in r.stderr and "Traceback" not in r.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == ["imgs"]  # nothing written


# -- kill -9 and Ctrl-C ------------------------------------------------------------------------

@pytest.mark.slow
def test_rows_of_a_killed_run_are_recovered_by_resume(tmp_path):
    n = 40
    paths = good_folder(tmp_path / "imgs", n)
    args = ["propose", "imgs", "--out", "out.jsonl", "--batch-size", "1", *FAST]
    proc = _start(args, tmp_path)
    tmp = _wait_for_rows(tmp_path, "out.jsonl", proc, rows=3)
    proc.kill()
    proc.communicate(timeout=30)
    finished = len(read_jsonl_lenient(tmp))
    assert finished >= 3
    # without --resume or --overwrite the finished rows are not thrown away silently
    r = reeb(*args, cwd=tmp_path, check_rc=2)
    assert "--resume" in r.stderr and tmp.name in r.stderr, r.stderr
    r = reeb(*args, "--resume", cwd=tmp_path, check_rc=0)
    assert f"{n - finished} to do" in r.stderr, r.stderr
    rows = read_jsonl(tmp_path / "out.jsonl")
    assert [r["image"] for r in rows] == [str(p.relative_to(tmp_path)) for p in paths]
    assert no_temp_files(tmp_path)


def read_jsonl_lenient(p: Path) -> list[dict]:
    rows = []
    for line in p.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return rows


@pytest.mark.slow
def test_interrupt_summary_counts_the_rows_in_the_file(tmp_path):
    import re

    good_folder(tmp_path / "imgs", 40)
    proc = _start(["propose", "imgs", "--out", "out.jsonl", "--batch-size", "1", *FAST], tmp_path)
    _wait_for_rows(tmp_path, "out.jsonl", proc, rows=2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    m = re.search(r"interrupted: (\d+) of 40 images saved", err)
    assert m, err
    assert int(m.group(1)) == len(read_jsonl(tmp_path / "out.jsonl"))


def test_interrupt_is_deferred_while_a_row_is_written():
    from reeb_torch.runs.ctrl_c import CriticalSection

    cs = CriticalSection()
    with pytest.raises(KeyboardInterrupt):
        with cs:
            cs.interrupt()  # what the signal handler calls
            done = True  # the write finishes first
    assert done
    with pytest.raises(KeyboardInterrupt):
        cs.interrupt()  # outside a write: at once


# -- row order, .json, sizes in error rows -----------------------------------------------------

@pytest.mark.slow
def test_rows_in_input_order_with_error_rows_and_sizes(tmp_path):
    d = tmp_path / "mix"
    d.mkdir()
    base = small_frame()
    cv2.imwrite(str(d / "a1.png"), base)
    (d / "a2.png").write_bytes(b"not an image")
    cv2.imwrite(str(d / "a3.png"), small_frame((96, 48)))
    cv2.imwrite(str(d / "a4.png"), base[:10, :12])  # smaller than the smallest window
    cv2.imwrite(str(d / "a5.png"), np.roll(base, 5, axis=1))
    r = reeb("propose", "mix", "-o", "o.jsonl", "-b", "2", *FAST, cwd=tmp_path, check_rc=1)
    rows = read_jsonl(tmp_path / "o.jsonl")
    assert [Path(r["image"]).name for r in rows] == ["a1.png", "a2.png", "a3.png", "a4.png", "a5.png"]
    assert [r["status"] == "ok" for r in rows] == [True, False, True, False, True]
    assert (rows[3]["width"], rows[3]["height"]) == (12, 10)  # the tiny image's size is known
    assert rows[1]["width"] is None
    for row in rows:
        assert set(row) == ROW_FIELDS and row["format_version"] == 2
    assert "3 ok, 2 failed" in r.stderr


@pytest.mark.slow
def test_json_output_is_refused_with_a_hint(tmp_path):
    good_folder(tmp_path / "imgs", 1)
    r = reeb("propose", "imgs", "-o", "x.json", *FAST, cwd=tmp_path, check_rc=2)
    assert ".jsonl" in r.stderr and "x.json" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imgs"]


@pytest.mark.slow
def test_parquet_rows_carry_the_schema(tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    good_folder(tmp_path / "imgs", 1)
    (tmp_path / "imgs" / "bad.png").write_bytes(b"x")
    reeb("propose", "imgs", "-o", "p.parquet", *FAST, cwd=tmp_path, check_rc=1)
    rows = pq.read_table(tmp_path / "p.parquet").to_pylist()
    assert [Path(r["image"]).name for r in rows] == ["bad.png", "frame_000.png"]
    assert set(rows[0]) == ROW_FIELDS and {r["format_version"] for r in rows} == {2}
    bad, good = rows
    assert bad["labels"] is None and bad["boxes"] == []
    assert len(good["labels"]) == len(good["boxes"]) > 0 and set(good["labels"]) <= set(KITTI_CLASSES)


@pytest.mark.slow
def test_rows_carry_class_hints_only_where_the_settings_give_them(tmp_path):
    good_folder(tmp_path / "imgs", 1)
    reeb("propose", "imgs", "-o", "free.jsonl", "--preset", "training-free", *FAST, cwd=tmp_path, check_rc=0)
    (free,) = read_jsonl(tmp_path / "free.jsonl")
    assert free["labels"] is None and len(free["boxes"]) > 0  # no ranker: no class head


@pytest.mark.slow
def test_resume_keeps_rows_of_the_previous_format(tmp_path):
    # a file written before the rows had labels (format 1): its rows are kept as they were,
    # the new image's row has them
    good_folder(tmp_path / "imgs", 2)
    reeb("propose", "imgs/frame_000.png", "-o", "p.jsonl", *FAST, cwd=tmp_path, check_rc=0)
    (old,) = read_jsonl(tmp_path / "p.jsonl")
    old = {k: v for k, v in old.items() if k != "labels"} | {"format_version": 1}
    (tmp_path / "p.jsonl").write_text(json.dumps(old) + "\n")
    reeb("propose", "imgs", "-o", "p.jsonl", "--resume", *FAST, cwd=tmp_path, check_rc=0)
    rows = {Path(r["image"]).name: r for r in read_jsonl(tmp_path / "p.jsonl")}
    assert rows["frame_000.png"] == old
    assert rows["frame_001.png"]["format_version"] == 2 and len(rows["frame_001.png"]["labels"]) > 0


# -- folder scan and reader agree --------------------------------------------------------------

def test_folder_scan_finds_every_format_the_reader_reads(tmp_path):
    from PIL import Image

    from reeb_torch.runs.inputs import find_images
    from reeb_torch.io import IMAGE_EXTENSIONS, read_image

    rgb = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "a.gif")
    assert ".gif" in IMAGE_EXTENSIONS
    images, _ = find_images([tmp_path])
    assert [p.name for p in images] == ["a.gif"]
    assert read_image(images[0]).shape == (3, 20, 30)
    for ext in IMAGE_EXTENSIONS:  # every listed extension decodes
        ok, buf = cv2.imencode(".pgm" if ext == ".pbm" else ext, rgb[:, :, :1] if ext in (".pgm", ".pbm") else rgb)
        if ok:
            (tmp_path / f"b{ext}").write_bytes(buf.tobytes())
            assert read_image(tmp_path / f"b{ext}").shape == (3, 20, 30), ext


# -- paths to the same file are named, not dropped silently ------------------------------------

def test_scan_names_the_paths_to_the_same_file(tmp_path):
    from reeb_torch.runs.inputs import same_file_note, scan_images

    real = good_folder(tmp_path / "real", 3)
    (tmp_path / "links").mkdir()
    for i in range(12):  # four links to each image
        (tmp_path / "links" / f"l{i:02d}.png").symlink_to(real[i % 3])
    found = scan_images([tmp_path / "links", real[0]])
    assert [p.name for p in found.images] == ["l00.png", "l01.png", "l02.png"]
    assert len(found.same_file) == 10
    assert found.same_file[0] == (tmp_path / "links" / "l03.png", tmp_path / "links" / "l00.png")
    assert found.same_file[-1] == (real[0], tmp_path / "links" / "l00.png")  # named twice: the first kept
    note = same_file_note(found.same_file)
    assert note == (f"skipped 10 paths, the same file as another: {tmp_path}/links/l03.png (= {tmp_path}/links/"
                    f"l00.png), {tmp_path}/links/l04.png (= {tmp_path}/links/l01.png), {tmp_path}/links/l05.png "
                    f"(= {tmp_path}/links/l02.png), and 7 more")
    assert found.notes == [note]


@pytest.mark.slow
def test_a_folder_of_links_says_how_many_paths_were_the_same_file(tmp_path):
    real = good_folder(tmp_path / "real", 2)
    (tmp_path / "links").mkdir()
    for i in range(8):
        (tmp_path / "links" / f"l{i}.png").symlink_to(real[i % 2])
    r = reeb("propose", "links", "-o", "o.jsonl", "-q", "--summary-json", "s.json", *FAST, cwd=tmp_path,
             check_rc=0)
    assert len(read_jsonl(tmp_path / "o.jsonl")) == 2
    lines = r.stderr.splitlines()
    assert lines[0].startswith("2 images: 2 ok"), r.stderr
    assert lines[1] == ("skipped 6 paths, the same file as another: links/l2.png (= links/l0.png), "
                        "links/l3.png (= links/l1.png), links/l4.png (= links/l0.png), and 3 more"), r.stderr
    assert json.loads((tmp_path / "s.json").read_text())["same_file"] == 6


# -- reeb eval without data --------------------------------------------------------------------

@pytest.mark.slow
def test_eval_without_frames_or_labels_is_a_usage_error(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "nolab" / "images").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "nolab" / "images" / "000001.png"), small_frame())
    for folder, words in (("empty", "not a KITTI folder"), ("nolab", "label")):
        r = reeb("eval", folder, "--limit", "1", cwd=tmp_path, check_rc=2)
        assert words in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr  # one line, no usage block


@pytest.mark.slow
def test_show_on_a_folder_is_a_usage_error(tmp_path):
    (tmp_path / "d").mkdir()
    r = reeb("show", "d", cwd=tmp_path, check_rc=2)
    assert "is a folder" in r.stderr, r.stderr


# -- reeb show keeps the aspect ratio ----------------------------------------------------------

@pytest.mark.parametrize("h, w", [(400, 60), (60, 400)])
def test_show_picture_keeps_the_aspect_ratio(h, w):
    pytest.importorskip("matplotlib")
    import torch

    from reeb_torch.generator import Inspection
    from reeb_torch.runs.viz import inspection_figure

    insp = Inspection(boxes=torch.tensor([[1.0, 2.0, 30.0, 40.0]]), scores=torch.tensor([1.0]),
                      edges=torch.zeros(h, w), road_mask=torch.zeros(h, w, dtype=torch.bool),
                      regions=torch.tensor([[0.0, 0.0, float(w), float(h)]]),
                      entropy=torch.tensor([1.0]), share=torch.tensor([1.0]), num_groups=1, num_windows=1)
    fig = inspection_figure(torch.zeros(3, h, w, dtype=torch.uint8), insp)
    fig.canvas.draw()
    images = [ax for ax in fig.axes if ax.images]
    assert len(images) == 3
    for ax in images:
        box = ax.get_window_extent()
        assert box.width / box.height == pytest.approx(w / h, rel=0.02)


def test_show_picture_names_the_ranking_it_shows():
    """Panel 3's title: the learned model's name under the default, eq. 12's terms without it."""
    pytest.importorskip("matplotlib")
    import torch

    from reeb_torch import ReebConfig, get_preset
    from reeb_torch.generator import Inspection
    from reeb_torch.runs.viz import inspection_figure

    h, w = 60, 200
    insp = Inspection(boxes=torch.tensor([[1.0, 2.0, 30.0, 40.0]]), scores=torch.tensor([1.0]),
                      edges=torch.zeros(h, w), road_mask=torch.zeros(h, w, dtype=torch.bool),
                      regions=torch.tensor([[0.0, 0.0, float(w), float(h)]]),
                      entropy=torch.tensor([1.0]), share=torch.tensor([1.0]), num_groups=1, num_windows=1)
    titles = {}
    for name, cfg in (("default", ReebConfig()), ("free", get_preset("training-free")),
                      ("file", ReebConfig().replace(ranker="/some/where/mine.safetensors"))):
        fig = inspection_figure(torch.zeros(3, h, w, dtype=torch.uint8), insp, config=cfg)
        titles[name] = [ax.get_title(loc="left") for ax in fig.axes if ax.get_title(loc="left").startswith("3.")][0]
    assert "learned model 'kitti'" in titles["default"]
    assert "learned model 'mine.safetensors'" in titles["file"]
    assert "learned" not in titles["free"] and "edge score S (eq. 1)" in titles["free"]


def test_an_interrupt_wrapped_by_a_library_is_still_an_interrupt():
    # numba, loading a cached kernel when Ctrl-C lands, re-raises it as a SystemError
    from reeb_torch.runs.ctrl_c import caused_by_interrupt

    def wrapped() -> None:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise SystemError("returned a result with an exception set") from e

    try:
        wrapped()
    except SystemError as e:
        assert caused_by_interrupt(e)
    assert caused_by_interrupt(KeyboardInterrupt())
    assert not caused_by_interrupt(ValueError("a bad image"))
    try:
        try:
            raise ValueError("inner")
        except ValueError:
            raise RuntimeError("outer")  # noqa: B904 - chained by context only
    except RuntimeError as e:
        assert not caused_by_interrupt(e)
