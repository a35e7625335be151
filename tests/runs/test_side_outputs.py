"""``--viz`` as a careless user would give it: the input folder itself, or a folder that
already holds pictures. An input image is never written over, whatever the options; a file
already there is replaced only with ``--overwrite`` (or ``--resume``). Each refusal is one
line, exit 2, before any work."""

from __future__ import annotations

import shutil
from pathlib import Path

from click.testing import CliRunner

from reeb_torch.runs.cli import main

SAMPLE = Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000001.png"


def _propose(*args):
    # decoding in this process: a DataLoader worker forked from a test process that other tests
    # left threads in (numba's, OpenCV's) can hang
    return CliRunner().invoke(main, ["propose", *map(str, args), "-q", "--set", "top_k=50", "--workers", "0"])


def test_viz_onto_the_input_folder_is_refused_and_the_input_kept(tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    shutil.copy(SAMPLE, imgs / "a.png")
    before = (imgs / "a.png").read_bytes()
    for extra in ([], ["--overwrite"]):
        res = _propose(imgs, "-o", tmp_path / "d.jsonl", "--viz", imgs, *extra)
        assert res.exit_code == 2, res.output
        assert "would be written over the input image" in res.output and "Traceback" not in res.output
        assert (imgs / "a.png").read_bytes() == before
    assert not (tmp_path / "d.jsonl").exists()


def test_viz_onto_pictures_already_there_needs_overwrite(tmp_path):
    imgs, pics = tmp_path / "imgs", tmp_path / "pics"
    imgs.mkdir()
    pics.mkdir()
    shutil.copy(SAMPLE, imgs / "a.png")
    (pics / "a.png").write_bytes(b"an earlier picture")
    res = _propose(imgs, "-o", tmp_path / "d.jsonl", "--viz", pics)
    assert res.exit_code == 2 and "holds a.png already; add --overwrite" in res.output, res.output
    assert (pics / "a.png").read_bytes() == b"an earlier picture"
    res = _propose(imgs, "-o", tmp_path / "d.jsonl", "--viz", pics, "--overwrite")
    assert res.exit_code == 0, res.output
    assert (pics / "a.png").read_bytes()[:4] == b"\x89PNG"


def test_calibrate_never_writes_its_picture_over_its_config_or_another_file(tmp_path):
    from tests.eval.test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")

    def calibrate(*args):
        return CliRunner().invoke(main, ["calibrate", str(data), "--samples", "20", *map(str, args)])

    res = calibrate("-o", tmp_path / "cam.png")
    assert res.exit_code == 2 and "the same file; name the config" in res.output, res.output
    assert not (tmp_path / "cam.png").exists()
    (tmp_path / "cam.png").write_bytes(b"someone's picture")
    res = calibrate("-o", tmp_path / "cam.json")
    assert res.exit_code == 2 and "cam.png exists; add --overwrite" in res.output, res.output
    assert (tmp_path / "cam.png").read_bytes() == b"someone's picture" and not (tmp_path / "cam.json").exists()
    (tmp_path / "afile").write_text("x")
    res = calibrate("-o", tmp_path / "afile" / "cam.json")
    assert res.exit_code == 2 and "is a file, not a folder" in res.output and "Traceback" not in res.output
