"""Eq. 2 entropy and eq. 9 proposal share."""

from __future__ import annotations

import math

import pytest
import torch

from reeb_torch.stages.entropy import proposal_share, region_entropy


def _entropy_ref(values: torch.Tensor, bins: int) -> float:
    level = (values * bins).long().clamp(0, bins - 1)
    p = torch.bincount(level.flatten(), minlength=bins).double()
    p = p[p > 0] / p.sum()
    return float(-(p * torch.log2(p)).sum())


def test_region_entropy_matches_bincount():
    gen = torch.Generator().manual_seed(0)
    gray = torch.rand(2, 1, 10, 40, generator=gen) ** 2
    bounds = torch.tensor([[0, 10], [5, 25], [20, 40]])
    got = region_entropy(gray, bounds, 256)
    for b in range(2):
        for r, (x0, x1) in enumerate(bounds.tolist()):
            assert float(got[b, r]) == pytest.approx(_entropy_ref(gray[b, 0, :, x0:x1], 256), abs=1e-4)


def test_entropy_extremes():
    flat = torch.full((1, 1, 8, 8), 0.5)
    assert float(region_entropy(flat, torch.tensor([[0, 8]]), 256)) == pytest.approx(0.0, abs=1e-6)
    ramp = (torch.arange(256).float() / 256).view(1, 1, 16, 16)
    assert float(region_entropy(ramp, torch.tensor([[0, 16]]), 256)) == pytest.approx(8.0, abs=1e-5)


def test_share_abs_diff():
    h = torch.tensor([0.0, 2.0, 4.0, 6.0, 8.0, 9.0])
    share = proposal_share(h, 4.0)
    assert share.tolist() == pytest.approx([0.0, 0.5, 1.0, 0.5, 0.0, 0.0])
    assert math.isclose(float(proposal_share(torch.tensor(3.0), 4.0)), 0.75)


def test_compiled_strip_histograms_equal_the_tensor_path():
    # the CPU pass counts the same grey levels per strip as the per-column tensor histograms
    import numpy as np

    from reeb_torch.stages.entropy import _strip_histograms, _strip_histograms_tensor

    gen = torch.Generator().manual_seed(4)
    grey = torch.rand(3, 17, 40, generator=gen)
    # the edges of the range and of the bins: 0, 1, exact multiples of 1/16 and their neighbours
    edge_values = torch.tensor([0.0, 1.0, 0.5, 1 / 16, 15 / 16, 0.9999999, 0.0625 - 1e-8, 0.0625 + 1e-8])
    grey.view(-1)[: len(edge_values)] = edge_values
    bounds = torch.tensor([[0, 10], [5, 25], [20, 40], [0, 40]])
    hist = np.zeros((3, 4, 16), np.float32)
    _strip_histograms(grey.numpy(), bounds.numpy(), 16, hist)
    level = (grey * 16).long().clamp_(0, 15)  # the tensor path's levels
    assert torch.equal(torch.from_numpy(hist), _strip_histograms_tensor(level, bounds, 16))
    assert float(hist[:, 3].sum()) == 3 * 17 * 40


def test_region_entropy_on_the_cpu_equals_the_tensor_path():
    # the compiled pass takes the grey levels itself: the same entropies as the tensor ops
    from reeb_torch.stages.entropy import _entropy_bits, _strip_histograms_tensor, region_entropy

    grey = torch.rand(4, 1, 30, 64, generator=torch.Generator().manual_seed(7))
    bounds = torch.tensor([[0, 20], [10, 40], [30, 64]])
    level = (grey[:, 0] * 256).long().clamp_(0, 255)
    assert torch.equal(region_entropy(grey, bounds), _entropy_bits(_strip_histograms_tensor(level, bounds, 256)))
