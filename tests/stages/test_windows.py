"""Sec. 3.6 sliding windows."""

from __future__ import annotations

import torch

from reeb_torch.stages.windows import window_grid, window_sizes


def test_sizes_respect_bounds_and_aspect():
    sizes = window_sizes(100, 300, 80, 10, 1.25, 0.15, (0.25, 4.0))
    assert sizes
    for s in sizes:
        assert 10 <= s.w <= 80 and 10 <= s.h <= 100 and 0.25 <= s.w / s.h <= 4.0
        assert s.sx == max(1, round(0.15 * s.w)) and s.sy == max(1, round(0.15 * s.h))
        assert (s.nx - 1) * s.sx + s.w <= 300 and s.nx * s.sx + s.w > 300
    assert 80 / 1.25 <= max(s.w for s in sizes) <= 80  # the series reaches the bound within one ratio


def test_grid_boxes_and_region_assignment():
    bounds = torch.tensor([[0, 50], [25, 75], [50, 100]])
    for assign in ("nearest", "contained"):
        g = window_grid(40, 100, bounds, 8, 1.3, 0.2, (0.5, 2.0), assign)
        assert g.boxes.shape == (g.count, 4)
        assert float(g.boxes[:, 2].max()) <= 100 and float(g.boxes[:, 3].max()) <= 40
        for r, idx in enumerate(g.region_windows):
            b = g.boxes[idx]
            if assign == "contained":
                assert bool((b[:, 0] >= bounds[r, 0]).all() and (b[:, 2] <= bounds[r, 1]).all())
        covered = torch.cat(g.region_windows).unique().numel()
        if assign == "nearest":
            assert covered == g.count and sum(i.numel() for i in g.region_windows) == g.count
        else:
            assert covered < g.count  # windows straddling two strips' edges fall in none (NOTES)


def test_ground_band_keeps_rows_where_height_fits_the_bottom_row():
    h_img, horizon, lo, hi = 200, 0.4, 0.5, 2.0
    sizes = window_sizes(h_img, 300, 300, 10, 1.3, 0.15, (0.25, 4.0), ground=(horizon, lo, hi))
    full = window_sizes(h_img, 300, 300, 10, 1.3, 0.15, (0.25, 4.0))
    assert sum(s.count for s in sizes) < sum(s.count for s in full)
    for s in sizes:
        for j in range(s.ny):
            bottom = s.oy + j * s.sy + s.h
            assert bottom <= h_img
            ratio = s.h / (bottom - horizon * h_img)
            assert lo - 1e-6 <= ratio <= hi + 1e-6
        # the first row excluded above and below breaks the band (or leaves the image)
        above = s.oy - s.sy + s.h
        assert above - horizon * h_img <= 0 or s.h / (above - horizon * h_img) > hi - 1e-6 or s.oy - s.sy < 0
