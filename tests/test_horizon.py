"""The horizon without labels (reeb_torch.horizon) on drawn roads and rooms and on KITTI frames
moved by the camera transform, and ``reeb calibrate``'s routes without labels (images,
intrinsics) with their bad inputs, each as one line."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from reeb_torch.horizon import (BOX_BOTTOM_OFFSET, FrameVanishingPoint, HorizonError, estimate_horizon,
                                frame_vanishing_point)

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples" / "data"


def road_frame(vp_row: float, vp_col: float = 0.5, h: int = 200, w: int = 480, seed: int = 0) -> np.ndarray:
    """``uint8 [h, w, 3]`` RGB: a road seen from on it, its edges and dashed lane markings
    meeting at ``(vp_col, vp_row)`` of the frame, under a sky, beside grass and a few boxes."""
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.uint8)
    vx, vy = vp_col * w, vp_row * h
    img[:] = (50, 95, 40)
    img[: int(vy)] = (180, 200, 230)
    cv2.fillPoly(img, [np.array([[vx, vy], [w * 1.1, h], [-w * 0.1, h]], np.int32)], (105, 105, 110))
    for at in (0.3, 0.7):
        xb = -w * 0.1 + at * w * 1.2
        for t0 in np.arange(0.15, 1.0, 0.17):
            p0 = (int(vx + (xb - vx) * t0), int(vy + (h - vy) * t0))
            p1 = (int(vx + (xb - vx) * (t0 + 0.11)), int(vy + (h - vy) * (t0 + 0.11)))
            cv2.line(img, p0, p1, (235, 235, 235), max(1, int(3 * (t0 + 0.11))))
    for _ in range(3):
        x, y = int(rng.uniform(0, w - 40)), int(rng.uniform(vy - 30, vy))
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        cv2.rectangle(img, (x, y), (x + int(rng.uniform(15, 40)), y + int(rng.uniform(10, 30))), colour, -1)
    return np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)


def room_frame(h: int = 150, w: int = 480, seed: int = 0) -> np.ndarray:
    """``uint8 [h, w, 3]`` RGB: a room (a wall lit from one side, a floor, pictures, a lamp); no road."""
    rng = np.random.default_rng(seed)
    img = np.array([200.0, 190, 170]) * (0.7 + 0.3 * np.linspace(0, 1, w)[None, :, None]) * np.ones((h, 1, 1))
    img[int(0.8 * h):] *= 0.6
    for _ in range(4):
        x, y = int(rng.uniform(0, w - 80)), int(rng.uniform(0, h * 0.6))
        colour = tuple(float(c) for c in rng.integers(0, 255, 3))
        cv2.rectangle(img, (x, y), (x + int(rng.uniform(30, 80)), y + int(rng.uniform(20, 50))), colour,
                      int(rng.integers(-1, 4)))
    cv2.circle(img, (int(w * 0.7), int(h * 0.4)), int(h * 0.15), (90, 60, 40), -1)
    return np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)


def _write(folder: Path, frames: list[np.ndarray]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:06d}.png"), f[:, :, ::-1])
    return folder


# -- the estimator -------------------------------------------------------------------------------

@pytest.mark.parametrize("row,col", [(0.45, 0.5), (0.38, 0.4), (0.55, 0.62), (0.30, 0.5)])
def test_a_drawn_roads_vanishing_point_is_found(row, col):
    p = frame_vanishing_point(road_frame(row, col, seed=int(100 * row)))
    assert abs(p.row - row) < 0.01 and abs(p.column - col) < 0.02, p
    assert p.road and p.support > 0.5 and p.left > 0 and p.right > 0


def test_images_come_as_tensors_or_arrays_alike():
    import torch

    rgb = road_frame(0.42)
    as_tensor = frame_vanishing_point(torch.from_numpy(rgb).permute(2, 0, 1).contiguous())
    as_float = frame_vanishing_point(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
    as_grey = frame_vanishing_point(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert as_tensor.row == frame_vanishing_point(rgb).row == as_grey.row
    assert abs(as_float.row - as_tensor.row) < 0.005
    with pytest.raises(ValueError, match="image"):
        frame_vanishing_point(torch.zeros(2, 5, 5))


def test_a_room_shows_no_road():
    for s in range(3):
        assert not frame_vanishing_point(room_frame(seed=s)).road


def test_the_horizon_is_the_mode_of_the_frames_plus_the_offset():
    rows = [0.40, 0.41, 0.40, 0.39, 0.40, 0.41, 0.40, 0.60]  # one frame's lines meet elsewhere
    frames = [road_frame(r, 0.5 + 0.02 * (i % 3), seed=i) for i, r in enumerate(rows)]
    est = estimate_horizon(frames, samples=200)
    assert abs(est.vanishing_row - 0.40) < 0.01 and est.horizon == pytest.approx(est.vanishing_row + BOX_BOTTOM_OFFSET)
    assert est.interval[0] <= est.horizon <= est.interval[1] and est.interval[1] - est.interval[0] < 0.03
    assert est.num_frames == 8 and est.num_road == 8 and est.agree == 7
    assert estimate_horizon(frames, samples=50, offset=0.0).horizon == pytest.approx(est.vanishing_row)


def test_too_few_frames_and_no_road_are_told_apart():
    with pytest.raises(HorizonError, match="2 frames: too few"):
        estimate_horizon([road_frame(0.4), road_frame(0.41)])
    with pytest.raises(HorizonError, match="no road seen: in 0 of 6 frames"):
        estimate_horizon([room_frame(seed=s) for s in range(6)])
    # a third of the frames must show a road
    road, none = FrameVanishingPoint(0.4, 0.5, 0.6, 0.2, 0.2, 20), FrameVanishingPoint(math.nan, 0, 0, 0, 0, 0)
    with pytest.raises(HorizonError, match="in 2 of 9 frames"):
        estimate_horizon((), points=[road] * 2 + [none] * 7)
    assert estimate_horizon((), points=[road] * 3 + [none] * 6, samples=10).num_road == 3
    with pytest.raises(ValueError, match="0 < level < 1"):
        estimate_horizon((), points=[road] * 5, level=1.5)


def _transform():
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import camera_transform
    finally:
        sys.path.pop(0)
    return camera_transform


def test_the_camera_transform_moves_pixels_labels_and_calibration_together(tmp_path):
    ct = _transform()
    src = tmp_path / "src"
    for sub, name, suffix in (("images", "kitti_000001.png", ".png"), ("labels", "kitti_000001.txt", ".txt"),
                              ("calib", "kitti_000001_calib.txt", ".txt")):
        (src / sub).mkdir(parents=True)
        shutil.copy(EXAMPLES / name, src / sub / f"000001{suffix}")
    t = ct.Transform(zoom=1.33, horizon_from=0.47, horizon_to=0.41)
    record = ct.transform_folder(src, tmp_path / "dst", t)
    assert record["frames"] == 1 and record["horizon"] == 0.41
    img = cv2.imread(str(tmp_path / "dst" / "images" / "000001.png"))
    assert img.shape[:2] == (375, 1242)
    sw, sh, x0, y0, ow, oh = ct.window(t, 1242, 375)
    assert abs((0.47 * 375 * 1.33 - y0) / oh - 0.41) < 0.003
    from reeb_torch.camera import Camera
    from reeb_torch.datasets.kitti import read_kitti_labels

    before = Camera.from_kitti_calib(src / "calib" / "000001.txt")
    after = Camera.from_kitti_calib(tmp_path / "dst" / "calib" / "000001.txt")
    assert after.fy == pytest.approx(1.33 * before.fy) and after.cy == pytest.approx(1.33 * before.cy - y0)
    old = read_kitti_labels(src / "labels" / "000001.txt")
    new = read_kitti_labels(tmp_path / "dst" / "labels" / "000001.txt")
    kept = [(o, n) for o, n in zip(old, new) if n.type == o.type and n.type != "DontCare"]
    assert kept and all(n.box[3] == pytest.approx(min(1.33 * o.box[3] - y0, oh - 1), abs=0.02) for o, n in kept)
    with pytest.raises(ValueError, match="leaves the"):
        ct.window(ct.Transform(zoom=1.0, horizon_from=0.47, horizon_to=0.2), 1242, 375)


@pytest.mark.slow
@pytest.mark.kitti
def test_kitti_frames_moved_by_the_transform_move_the_estimate_with_them(kitti_dir, tmp_path):
    """On KITTI frames the estimate lies in the labelled fit's interval (0.465-0.479); zoomed
    by 1.33 with the horizon moved to 0.41 and cropped to 0.55, it moves with them."""
    ct = _transform()
    from reeb_torch import read_image
    from reeb_torch.datasets.kitti import KittiDataset

    ids = KittiDataset(kitti_dir).ids[:24]
    src = tmp_path / "src"
    for sub, suffix in (("images", ".png"), ("labels", ".txt"), ("calib", ".txt")):
        (src / sub).mkdir(parents=True)
        for i in ids:
            shutil.copy(kitti_dir / sub / f"{i}{suffix}", src / sub / f"{i}{suffix}")
    plain = estimate_horizon([read_image(p) for p in sorted((src / "images").iterdir())], samples=50)
    assert 0.465 <= plain.horizon <= 0.479, plain
    for name, t in (("zoom", ct.Transform(1.33, None, 0.4714, 0.41)), ("crop", ct.Transform(1.0, (1100, 300), 0.4714,
                                                                                               0.55))):
        ct.transform_folder(src, tmp_path / name, t)
        moved = estimate_horizon([read_image(p) for p in sorted((tmp_path / name / "images").iterdir())], samples=50)
        assert abs(moved.horizon - t.horizon_to) < 0.01, (name, moved)


# -- reeb calibrate without labels ----------------------------------------------------------------

def _cli(args, **kw):
    from reeb_torch.runs.cli import main

    return CliRunner().invoke(main, ["calibrate", *args], **kw)


def test_calibrate_a_folder_of_images_writes_the_camera_file(tmp_path):
    from reeb_torch.runs.common import build_config

    folder = _write(tmp_path / "frames", [road_frame(0.40 + 0.005 * (i % 3), seed=i) for i in range(7)])
    out = tmp_path / "camera.json"
    res = _cli([str(folder), "-o", str(out), "--samples", "50"])
    assert res.exit_code == 0, res.output
    assert "route            images without labels" in res.output and "interval" in res.output
    assert "road seen in 7" in res.output
    record = json.loads(out.read_text())
    assert record["fit"]["route"] == "images" and record["fit"]["num_frames"] == 7
    cfg = build_config("default", str(out), (), None)  # what reeb propose --config reads
    assert abs(cfg.horizon - 0.405 - BOX_BOTTOM_OFFSET) < 0.01 and cfg.camera_height_m == 1.65
    again = [str(folder), "-o", str(out), "--samples", "20", "--camera-height", "1.4"]
    res = _cli(again)  # a file there already: replaced only with --overwrite
    assert res.exit_code == 2 and "add --overwrite" in res.output and json.loads(out.read_text()) == record
    res = _cli([*again, "--overwrite"])
    assert res.exit_code == 0 and json.loads(out.read_text())["config"]["camera_height_m"] == 1.4
    assert "1.400 m (given)" in res.output


@pytest.mark.kitti
def test_calibrate_no_labels_on_kitti_falls_in_the_labelled_interval(kitti_dir, tmp_path):
    out = tmp_path / "c.json"
    res = _cli([str(kitti_dir), "--no-labels", "-o", str(out), "--samples", "50"])
    assert res.exit_code == 0, res.output
    assert 0.465 <= json.loads(out.read_text())["config"]["horizon"] <= 0.479  # the labelled fit's 95 % interval


def test_calibrate_from_intrinsics(tmp_path):
    out = tmp_path / "c.json"
    res = _cli(["--cy", "150", "--height", "300", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "route            intrinsics" in res.output and json.loads(out.read_text())["config"]["horizon"] == 0.5
    calib = EXAMPLES / "kitti_000001_calib.txt"
    res = _cli(["--calib", str(calib), "--height", "375", "-o", str(out), "--overwrite"])
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["config"]["horizon"] == pytest.approx(172.854 / 375)
    frames = _write(tmp_path / "f", [np.zeros((300, 400, 3), np.uint8)])  # the height from the images
    res = _cli(["--calib", str(calib), str(frames), "-o", str(out), "--camera-height", "2", "--overwrite"])
    assert res.exit_code == 0, res.output
    record = json.loads(out.read_text())
    assert record["config"] == {"horizon": pytest.approx(172.854 / 300), "camera_height_m": 2.0}
    assert record["fit"]["route"] == "intrinsics" and record["fit"]["image_height_px"] == 300


def _one_error_line(res, *words):
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and all(w in lines[0] for w in words), res.output


def test_bad_input_gets_one_line(tmp_path):
    few = _write(tmp_path / "few", [road_frame(0.4, seed=i) for i in range(2)])
    _one_error_line(_cli([str(few), "-o", str(tmp_path / "c.json")]), "2 frames: too few", "at least 5")
    rooms = _write(tmp_path / "rooms", [room_frame(seed=s) for s in range(6)])
    _one_error_line(_cli([str(rooms), "-o", str(tmp_path / "c.json")]), "no road seen", "0 of 6 frames")
    no_p2 = EXAMPLES / "kitti_000001.txt"  # a label file, not a calibration
    _one_error_line(_cli(["--calib", str(no_p2), "--height", "375", "-o", str(tmp_path / "c.json")]),
                    "no P2 matrix")
    _one_error_line(_cli(["--cy", "100"]), "--cy needs --height")
    _one_error_line(_cli(["--cy", "500", "--height", "375"]), "outside the image height")
    _one_error_line(_cli(["-o", str(tmp_path / "c.json")]), "give folders")
    assert not (tmp_path / "c.json").exists()


def test_an_indoor_photograph_shows_no_road(tmp_path):
    mpl = pytest.importorskip("matplotlib")
    photo = Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    if not photo.exists():
        pytest.skip("matplotlib's sample photograph is not installed")
    folder = tmp_path / "indoor"
    folder.mkdir()
    for i in range(5):
        shutil.copy(photo, folder / f"{i}.jpg")
    _one_error_line(_cli([str(folder), "-o", str(tmp_path / "c.json")]), "no road seen")


def test_a_labelled_folder_takes_the_labelled_route_unless_told(tmp_path):
    folder = tmp_path / "k"
    (folder / "images").mkdir(parents=True)
    (folder / "labels").mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / "images" / f"{i:06d}.png"), road_frame(0.45, seed=i)[:, :, ::-1])
        (folder / "labels" / f"{i:06d}.txt").write_text("")
    res = _cli([str(folder), "-o", str(tmp_path / "c.json")])  # labelled route: no box to fit
    assert res.exit_code == 2 and "no usable labelled box" in res.output
    _one_error_line(_cli([str(folder), "--camera-height", "1.5"]), "--camera-height", "fits the camera height")
    res = _cli([str(folder), "--no-labels", "-o", str(tmp_path / "c.json"), "--samples", "20"])
    assert res.exit_code == 0 and "images without labels" in res.output, res.output
