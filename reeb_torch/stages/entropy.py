"""Eq. 2 — Shannon entropy of each region, and eq. 9 — the share of the region's
proposal budget it earns."""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ._threads import images_or_rows

__all__ = ["region_entropy", "proposal_share"]


def region_entropy(gray: Tensor, bounds: Tensor, bins: int = 256) -> Tensor:
    """Shannon entropy in bits (eq. 2) of the grey levels of each region.

    Args:
        gray: ``(B, 1, H, W)`` or ``(B, H, W)`` in [0, 1].
        bounds: ``int64 [R, 2]`` column ranges (start inclusive, end exclusive), full height.
        bins: grey levels ``M`` (256 = 8-bit); H lies in [0, log2(bins)].

    Returns: ``float [B, R]``.
    """
    g = gray.reshape(gray.shape[0], -1, gray.shape[-1]) if gray.ndim == 4 else gray
    b, h, w = g.shape
    if g.device.type == "cpu" and g.dtype == torch.float32:
        # one compiled pass per image over each strip, grey levels taken as it goes (the
        # same levels and integer counts), the two halves of the batch (or of one image's
        # strips) on two cores
        hist_np = np.zeros((b, bounds.shape[0], bins), np.float32)
        src = g.contiguous().numpy()
        bnd = bounds.to(torch.int64).contiguous().numpy()
        images_or_rows(lambda lo, hi, r0, r1: _strip_histograms(src[lo:hi], bnd[r0:r1], int(bins),
                                                                hist_np[lo:hi, r0:r1]), b, bnd.shape[0])
        return _entropy_bits(torch.from_numpy(hist_np))
    level = (g * bins).long().clamp_(0, bins - 1)  # (B, H, W)
    return _entropy_bits(_strip_histograms_tensor(level, bounds, bins))


def _strip_histograms_tensor(level: Tensor, bounds: Tensor, bins: int) -> Tensor:
    """Grey-level counts ``(B, R, bins)`` of the strips, as tensor ops (any device)."""
    b, h, w = level.shape
    dev = level.device
    # per-column histograms, then column prefix sums: a strip's histogram is a difference
    flat = (torch.arange(b, device=dev).view(b, 1, 1) * w + torch.arange(w, device=dev).view(1, 1, w)) * bins + level
    cols = torch.zeros(b * w * bins, dtype=torch.float32, device=dev)
    cols.index_add_(0, flat.reshape(-1), torch.ones(flat.numel(), device=dev))
    cum = torch.cat([cols.new_zeros(b, 1, bins), cols.view(b, w, bins).cumsum(1)], 1)  # (B, W+1, bins)
    bnd = bounds.to(dev)
    return cum[:, bnd[:, 1]] - cum[:, bnd[:, 0]]  # (B, R, bins)


def _entropy_bits(hist: Tensor) -> Tensor:
    """Eq. 2 from grey-level counts ``(B, R, bins)``: ``float [B, R]``, bits."""
    p = hist / hist.sum(-1, keepdim=True).clamp_min(1)
    return -(p * torch.log2(p.clamp_min(1e-30))).sum(-1)


@numba.njit(cache=True, nogil=True)
def _strip_histograms(gray: np.ndarray, bounds: np.ndarray, bins: int, hist: np.ndarray) -> None:  # pragma: no cover
    """Counts of each grey level in each column strip ``[bounds[r, 0], bounds[r, 1])`` of
    float32 ``gray`` ``(B, H, W)``; a pixel's level is ``(g · bins).long().clamp_(0, bins − 1)``
    as the tensor path takes it (a float32 product, truncated)."""
    fb = np.float32(bins)
    top = bins - 1
    part = np.zeros((4, bins), np.int64)  # four counts per level, for pixels 4t .. 4t + 3 of a row:
    # no pixel waits for the last one's add to the same level (exact integers, any order)
    for b in range(gray.shape[0]):
        for r in range(bounds.shape[0]):
            part.fill(0)
            for y in range(gray.shape[1]):
                line = gray[b, y, bounds[r, 0]: bounds[r, 1]]  # (indexed from 0: no negative-index test)
                for x in range(line.shape[0]):
                    lv = int(line[x] * fb)
                    lv = 0 if lv < 0 else (top if lv > top else lv)
                    part[x & 3, lv] += 1
            counts = hist[b, r]
            for lv in range(bins):
                counts[lv] += np.float32((part[0, lv] + part[1, lv]) + (part[2, lv] + part[3, lv]))


def proposal_share(entropy: Tensor, sigma: float = 4.0) -> Tensor:
    """Eq. 9: the fraction in [0, 1] of a region's maximum number of proposals,
    1 − |σ − H|/σ where |σ − H| ≤ σ, else 0 — highest at H = σ (reading 9: the printed
    |σ + H| gives no proposals for any H > 0).
    """
    d = (sigma - entropy).abs()
    return torch.where(d <= sigma, 1.0 - d / sigma, torch.zeros_like(entropy))
