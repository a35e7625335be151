"""reeb_torch.camera.fit_camera and ``reeb calibrate``: a known camera is recovered from
synthetic boxes, outliers do not move it, bad input is refused with a message."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from reeb_torch.camera import KITTI_CLASS_HEIGHTS_M, fit_camera

H_IMG = 375
FY = 721.5


def _synthetic(horizon=0.47, cam=1.65, frames=20, per_frame=8, noise_px=1.0, seed=0):
    """Boxes of cars and pedestrians standing on a flat road in front of a known camera."""
    rng = np.random.default_rng(seed)
    boxes, classes = [], []
    for _ in range(frames):
        b, c = [], []
        for _ in range(per_frame):
            name = "Car" if rng.random() < 0.7 else "Pedestrian"
            z = rng.uniform(6, 50)
            h = FY * KITTI_CLASS_HEIGHTS_M[name] / z
            bottom = horizon * H_IMG + FY * cam / z + rng.normal(0, noise_px)
            x1 = rng.uniform(0, 1000)
            b.append((x1, bottom - h, x1 + h, bottom))
            c.append(name)
        boxes.append(np.array(b))
        classes.append(c)
    return boxes, classes


def test_known_camera_is_recovered():
    boxes, classes = _synthetic(horizon=0.45, cam=1.8)
    fit = fit_camera(boxes, classes, H_IMG, samples=100, box_height_factor=1.0)
    assert fit.horizon == pytest.approx(0.45, abs=0.003)
    assert fit.camera_height_m == pytest.approx(1.8, abs=0.03)
    assert fit.horizon_interval[0] <= fit.horizon <= fit.horizon_interval[1]
    assert fit.camera_height_interval[0] <= fit.camera_height_m <= fit.camera_height_interval[1]
    assert set(fit.per_class) == {"Car", "Pedestrian"}
    assert abs(fit.per_class["Car"].median_px) < 1.0
    assert fit.per_class["Pedestrian"].implied_height_m == pytest.approx(KITTI_CLASS_HEIGHTS_M["Pedestrian"], rel=0.05)
    assert fit.config_changes() == {"horizon": fit.horizon, "camera_height_m": fit.camera_height_m}


def test_outliers_get_no_weight():
    boxes, classes = _synthetic(horizon=0.47, cam=1.65, seed=1)
    rng = np.random.default_rng(2)
    n_out = 0
    for b in boxes:  # a fifth of the objects sit 25-60 px too high (hills, sitting, mislabelled)
        for row in b:
            if rng.random() < 0.2:
                row[[1, 3]] -= rng.uniform(25, 60)
                n_out += 1
    fit = fit_camera(boxes, classes, H_IMG, samples=100, box_height_factor=1.0)
    assert fit.horizon == pytest.approx(0.47, abs=0.004)
    assert fit.camera_height_m == pytest.approx(1.65, abs=0.05)
    assert fit.num_outliers >= 0.8 * n_out
    # plain least squares on the same boxes is pulled away (the test can fail)
    x, y = fit.x, fit.y
    slope, intercept = np.polyfit(x, y, 1)
    assert abs(intercept - 0.47) > 0.01 or abs(slope - 1.65) > 0.1


def test_box_height_factor_scales_the_camera():
    boxes, classes = _synthetic(horizon=0.47, cam=1.65)
    plain = fit_camera(boxes, classes, H_IMG, samples=10, box_height_factor=1.0)
    tall = fit_camera(boxes, classes, H_IMG, samples=10, box_height_factor=1.1)
    assert tall.horizon == pytest.approx(plain.horizon)
    assert tall.camera_height_m == pytest.approx(1.1 * plain.camera_height_m)


def test_boxes_cut_by_the_border_are_left_out():
    boxes, classes = _synthetic(frames=5)
    boxes[0] = np.vstack([boxes[0], [10, 200, 100, H_IMG - 1]])  # its bottom row is the image's: cut
    classes[0] = classes[0] + ["Car"]
    assert fit_camera(boxes, classes, H_IMG, samples=10, box_height_factor=1.0).num_boxes == 5 * 8


@pytest.mark.parametrize("change, message", [
    (dict(classes=[["Misc"] * 8] * 20), "no usable labelled box"),
    (dict(frames=1, per_frame=20), "one frame"),
    (dict(frames=2, per_frame=2), "only 4 usable boxes"),
])
def test_bad_input_is_refused(change, message):
    classes = change.pop("classes", None)
    boxes, cls = _synthetic(**change)
    with pytest.raises(ValueError, match=message):
        fit_camera(boxes, classes or cls, H_IMG, samples=10)


def test_mismatched_inputs_are_refused():
    boxes, classes = _synthetic(frames=3)
    with pytest.raises(ValueError, match="3 frames of boxes but 2"):
        fit_camera(boxes, classes[:2], H_IMG)
    with pytest.raises(ValueError, match="class_heights"):
        fit_camera(boxes, classes, H_IMG, class_heights={"Car": -1})
    with pytest.raises(ValueError, match="box_height_factor"):
        fit_camera(boxes, classes, H_IMG, box_height_factor=0)
    with pytest.raises(ValueError, match="same height ratio"):
        same = [np.array([[0, 100, 50, 150.0]] * 4) for _ in range(3)]
        fit_camera(same, [["Car"] * 4] * 3, H_IMG, samples=5)


def test_cli_calibrate_kitti(kitti_dir, tmp_path):
    from reeb_torch.runs.cli import main
    from reeb_torch.runs.common import build_config

    out = tmp_path / "camera.json"
    res = CliRunner().invoke(main, ["calibrate", str(kitti_dir), "-o", str(out), "--samples", "30"])
    assert res.exit_code == 0, res.output
    assert "horizon" in res.output and "P2 horizon" in res.output and "Car" in res.output
    assert "route            labelled boxes" in res.output
    record = json.loads(out.read_text())
    cfg = build_config("default", str(out), (), None)  # what reeb propose --config reads
    assert cfg.horizon == record["config"]["horizon"]
    assert 0.46 < cfg.horizon < 0.48 and 1.6 < cfg.camera_height_m < 1.7  # KITTI: cy/H ~ 0.466, 1.65 m
    assert "box height factor" in res.output
    pytest.importorskip("matplotlib")
    assert (tmp_path / "camera.png").stat().st_size > 1000


def test_cli_calibrate_a_folder_without_labels_takes_the_images_route(tmp_path):
    from reeb_torch.runs.cli import main

    (tmp_path / "images").mkdir()
    shutil.copy("examples/data/kitti_000001.png", tmp_path / "images" / "000001.png")
    res = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "c.json")])
    assert res.exit_code == 2 and "1 frame: too few to estimate the horizon from images" in res.output
    res = CliRunner().invoke(main, ["calibrate", str(tmp_path), "--class-height", "Car=-2"])
    assert res.exit_code == 2 and "CLASS=METRES" in res.output


@pytest.mark.parametrize("args, option", [
    (["calibrate", "--cy", "inf", "--height", "375"], "--cy"),
    (["calibrate", "--cy", "180", "--height", "375", "--camera-height", "nan"], "--camera-height"),
    (["calibrate", "--cy", "180", "--height", "375", "--box-factor", "nan"], "--box-factor"),
])
def test_a_number_that_is_not_finite_is_a_usage_error(args, option, tmp_path):
    from reeb_torch.runs.cli import main

    res = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "camera.json")])
    assert res.exit_code == 2 and f"'{option}'" in res.output and "not a finite number" in res.output, res.output
    assert not (tmp_path / "camera.json").exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_calib_that_is_no_file_or_never_ends_is_one_line(tmp_path):
    """A FIFO (which would block) and /dev/zero (which never ends) as --calib: refused at
    once, one line, exit 2; a binary file: one line naming it."""
    from click.testing import CliRunner

    from reeb_torch.runs.cli import main

    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    binary = tmp_path / "b.txt"
    binary.write_bytes(b"P2: \x80\x81 1 2\n")
    for calib, words in ((fifo, "not a regular file"), ("/dev/zero", "not a regular file"),
                         (binary, "not a text file")):
        res = CliRunner().invoke(main, ["calibrate", "--calib", str(calib), "--height", "375",
                                        "-o", str(tmp_path / "c.json")])
        assert res.exit_code == 2 and words in res.output and str(calib) in res.output, res.output
        assert "Traceback" not in res.output
