"""Sec. 3.5 road segmentation."""

from __future__ import annotations

import torch

from reeb_torch.stages.road import road_mask, sample_positions


def test_samples_are_seeded_and_inside_the_band():
    a = sample_positions(100, 200, 300, (0.3, 0.8, 0.7, 1.0), seed=3)
    b = sample_positions(100, 200, 300, (0.3, 0.8, 0.7, 1.0), seed=3)
    assert torch.equal(a, b)
    ys, xs = a // 200, a % 200
    assert bool(((ys >= 80) & (ys < 100) & (xs >= 60) & (xs < 140)).all())
    assert not torch.equal(a, sample_positions(100, 200, 300, (0.3, 0.8, 0.7, 1.0), seed=4))


def test_grey_road_under_coloured_scene():
    img = torch.zeros(1, 3, 60, 80)
    img[:, 0] = 0.9  # red everywhere ...
    img[:, :, 35:, 10:70] = 0.45  # ... but a grey road at the bottom centre
    m = road_mask(img, samples=200)
    assert m.shape == (1, 60, 80) and m.dtype == torch.bool
    assert bool(m[0, 40:, 20:60].all())
    assert not bool(m[0, :30].any())
