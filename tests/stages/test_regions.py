"""Sec. 3.6, eqs. 5-8: region division from the camera."""

from __future__ import annotations

import math

import pytest

from reeb_torch import ReebConfig
from reeb_torch.stages.regions import region_bounds, region_count, region_width_fraction


def test_kitti_defaults_give_seven_quarter_width_strips():
    wr_raw = region_width_fraction(1.65, 35.0, 90.0, 2.55, round_to=None)
    d = 1.65 / math.tan(math.radians(17.5))
    assert d == pytest.approx(5.233, abs=1e-3)
    assert wr_raw == pytest.approx(2.55 / (2 * d), rel=1e-9)  # eq. 7 with M = d (θh = 90°)
    assert wr_raw == pytest.approx(0.2436, abs=1e-4)  # eqs. 5–7: ≈ 24.4 %
    wr = region_width_fraction(1.65, 35.0, 90.0, 2.55, round_to=0.125)
    assert wr == 0.25
    assert region_count(wr, 0.5) == 7  # eq. 8 corrected
    b = region_bounds(1242, wr, 0.5)
    assert b.shape == (7, 2)
    assert b[0, 0] == 0 and b[-1, 1] == 1242
    widths = (b[:, 1] - b[:, 0]).tolist()
    assert all(abs(w - 0.25 * 1242) <= 1 for w in widths)
    strides = (b[1:, 0] - b[:-1, 0]).tolist()
    assert all(abs(s - 0.125 * 1242) <= 1 for s in strides)


def test_unrounded_width_still_covers_the_image():
    wr = region_width_fraction(1.65, 35.0, 90.0, 2.55, round_to=None)
    n = region_count(wr, 0.5)
    assert n == 8
    b = region_bounds(1000, wr, 0.5)
    assert b[0, 0] == 0 and b[-1, 1] == 1000
    assert bool(((b[1:, 0] - b[:-1, 1]) <= 0).all())  # consecutive strips overlap


def test_wide_objects_give_one_region():
    assert region_width_fraction(1.65, 35.0, 20.0, 10.0) == 1.0
    assert region_count(1.0, 0.5) == 1
    assert region_bounds(640, 1.0, 0.5).tolist() == [[0, 640]]


def test_with_camera_from_kitti_p2():
    cfg = ReebConfig().with_camera(fx=721.5377, fy=721.5377, width=1242, height=375)
    assert cfg.horizontal_fov_deg == pytest.approx(2 * math.degrees(math.atan(621 / 721.5377)))
    assert 80 < cfg.horizontal_fov_deg < 82 and 28 < cfg.vertical_fov_deg < 30
    with pytest.raises(ValueError, match="positive"):
        ReebConfig().with_camera(fx=0, fy=1, width=10, height=10)


def test_with_kitti_calib_reads_p2(tmp_path):
    from pathlib import Path

    sample = Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000001_calib.txt"
    cfg = ReebConfig().with_kitti_calib(str(sample), 1242, 375)
    # P2 of KITTI frame 000001: fx = fy = 721.5377, cy = 172.854 -> horizon at row 172.854 / 375
    assert cfg == ReebConfig().with_camera(721.5377, 721.5377, 1242, 375, cy=172.854)
    assert cfg.horizon == pytest.approx(172.854 / 375)
    with pytest.raises(ValueError, match="principal row"):
        ReebConfig().with_camera(721.5, 721.5, 1242, 375, cy=400.0)
    bad = tmp_path / "calib.txt"
    bad.write_text("P0: " + " ".join(["1"] * 12) + "\n")
    with pytest.raises(ValueError, match="no P2"):
        ReebConfig().with_kitti_calib(str(bad), 1242, 375)
