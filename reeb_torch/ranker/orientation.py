"""Edge-orientation columns of the learned ranking's features (not in the paper).

REEB's edge map holds how strong an edge is, not which way it runs, so a box over a rail bed
or a kerb (long diagonal lines crossing it) and a box around a car (horizontal edges at its
top and bottom, vertical ones at its sides) can read alike. These columns split the
gradient energy of the working grey image (Sobel, the magnitude unclipped) into four
orientation bins and give, for each box, each bin's share inside the box and in its inner
border band (the box less the box shrunk by :data:`~reeb_torch.ranker.features.BORDER` of its
side on each side): eight numbers in [0, 1].

Bins, by the gradient's direction ``θ = atan2(gy, gx)`` modulo π, each π/4 wide: 0 around
0 (the gradient across: vertical edges), 1 around π/4 (``gx · gy > 0``), 2 around π/2
(horizontal edges), 3 around 3π/4 (``gx · gy < 0``).

A model reads these columns where its feature names hold them (``reeb fit`` fits them by
default; ``reeb fit --no-orientation`` leaves them out); the generator computes them only for
such a model. Tensor ops, the same on every device.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["ORIENTATION_NAMES", "orientation_integrals", "orientation_features"]

ORIENTATION_NAMES: tuple[str, ...] = (tuple(f"orient_in_{k}" for k in range(4))
                                      + tuple(f"orient_band_{k}" for k in range(4)))
"""The orientation columns, after :func:`~reeb_torch.ranker.features.feature_names`'s."""

_TAN = math.tan(math.pi / 8)
_EPS = 1e-6


def orientation_integrals(grey: Tensor) -> Tensor:
    """``float64 (B, 4, h + 1, w + 1)``: the integral image of each orientation bin's gradient
    magnitude of the grey images ``(B, h, w)`` (Sobel / 8, replicated borders)."""
    g = F.pad(grey.double()[:, None], (1, 1, 1, 1), mode="replicate")
    kx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=torch.float64,
                      device=grey.device) / 8
    gx = F.conv2d(g, kx[None, None])[:, 0]
    gy = F.conv2d(g, kx.T.contiguous()[None, None])[:, 0]
    mag = torch.sqrt(gx * gx + gy * gy)
    ax, ay = gx.abs(), gy.abs()
    vertical = ay <= _TAN * ax
    horizontal = ~vertical & (ax <= _TAN * ay)
    rising = ~vertical & ~horizontal & (gx * gy > 0)
    falling = ~vertical & ~horizontal & ~rising
    zero = torch.zeros_like(mag)
    bins = torch.stack([torch.where(m, mag, zero) for m in (vertical, rising, horizontal, falling)], 1)
    b, _, h, w = bins.shape
    ii = torch.zeros(b, 4, h + 1, w + 1, dtype=torch.float64, device=grey.device)
    ii[:, :, 1:, 1:] = bins.cumsum(3).cumsum(2)
    return ii


def _sums(ii: Tensor, bi: Tensor, x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor) -> Tensor:
    """Each bin's sum over the boxes ``[x0, x1) × [y0, y1)`` of images ``bi``: ``float64 [K, 4]``."""
    return ii[bi, :, y1, x1] - ii[bi, :, y0, x1] - ii[bi, :, y1, x0] + ii[bi, :, y0, x0]


def orientation_features(ii: Tensor, boxes: Tensor, bi: Tensor) -> Tensor:
    """The columns :data:`ORIENTATION_NAMES` of ``int64 [K, 4]`` working-pixel boxes
    ``(x0, y0, x1, y1)`` (ends exclusive) of images ``bi`` ``int64 [K]``, from
    :func:`orientation_integrals`' ``ii``: ``float32 [K, 8]``, each bin's share of the
    gradient energy inside the box (4), then in its inner border band (4)."""
    from .features import BORDER, _grown

    h, w = ii.shape[-2] - 1, ii.shape[-1] - 1
    x0, y0, x1, y1 = boxes.unbind(1)
    inside = _sums(ii, bi, x0, y0, x1, y1)
    band = inside - _sums(ii, bi, *_grown(x0, y0, x1, y1, -BORDER, h, w))
    return torch.cat([inside / (inside.sum(1, keepdim=True) + _EPS),
                      band / (band.sum(1, keepdim=True) + _EPS)], 1).float()
