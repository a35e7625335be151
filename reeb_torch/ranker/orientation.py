"""Edge-orientation columns of the learned ranking's features (not in the paper).

REEB's edge map holds how strong an edge is, not which way it runs, so a box over a rail bed
or a kerb (long diagonal lines crossing it) and a box around a car (horizontal edges at its
top and bottom, vertical ones at its sides) can read alike. These columns split the
gradient energy of the working grey image (Sobel / 8 with replicated borders, the magnitude
unclipped) into four orientation bins and give, for each box, each bin's share inside the box
and in its inner border band (the box less the box shrunk by
:data:`~reeb_torch.ranker.features.BORDER` of its side on each side): eight numbers in [0, 1].

Bins, by the gradient's direction ``θ = atan2(gy, gx)`` modulo π, each π/4 wide: 0 around
0 (the gradient across: vertical edges), 1 around π/4 (``gx · gy > 0``), 2 around π/2
(horizontal edges), 3 around 3π/4 (``gx · gy < 0``).

A model reads these columns where its feature names hold them (``reeb fit`` fits them by
default; ``reeb fit --no-orientation`` leaves them out); the generator computes them only for
such a model. On the CPU two compiled passes (the tables, then the boxes), elsewhere tensor
ops in the same order of operations: every pixel in the same bin, the sums equal to float64
rounding (torch's running sums may add in another order).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..stages import _scratch
from ..stages._threads import on_two_cores
from .features import BORDER, _grow, _grown

__all__ = ["ORIENTATION_NAMES", "orientation_integrals", "orientation_features"]

ORIENTATION_NAMES: tuple[str, ...] = (tuple(f"orient_in_{k}" for k in range(4))
                                      + tuple(f"orient_band_{k}" for k in range(4)))
"""The orientation columns, after :func:`~reeb_torch.ranker.features.feature_names`'s."""

_TAN = math.tan(math.pi / 8)
_EPS = 1e-6


def orientation_integrals(grey: Tensor) -> Tensor:
    """``float64 (B, h + 1, w + 1, 4)``: the integral image of each orientation bin's gradient
    magnitude of the grey images ``(B, h, w)`` (the bins last, so a corner's four sums share
    a cache line). On the CPU inside a generator's call, a scratch buffer the next batch
    reuses (:mod:`reeb_torch.stages._scratch`): valid for this batch only."""
    b, h, w = grey.shape
    if grey.device.type == "cpu":
        src = grey.float().contiguous().numpy()
        out = _scratch.empty("orientation.tables", (b, h + 1, w + 1, 4))  # reused batch after batch
        on_two_cores(lambda lo, hi: _integrals_kernel(src[lo:hi], out[lo:hi]), b)
        return torch.from_numpy(out)
    return _integrals_tensor(grey)


def _integrals_tensor(grey: Tensor) -> Tensor:
    """:func:`orientation_integrals` as tensor ops (any device)."""
    b, h, w = grey.shape
    p = F.pad(grey.double()[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    ul, uc, ur = p[:, :-2, :-2], p[:, :-2, 1:-1], p[:, :-2, 2:]
    ml, mr = p[:, 1:-1, :-2], p[:, 1:-1, 2:]
    dl, dc, dr = p[:, 2:, :-2], p[:, 2:, 1:-1], p[:, 2:, 2:]
    gx = (ur + 2.0 * mr + dr - ul - 2.0 * ml - dl) * 0.125  # the kernel's order of operations
    gy = (dl + 2.0 * dc + dr - ul - 2.0 * uc - ur) * 0.125
    mag = torch.sqrt(gx * gx + gy * gy)
    ax, ay = gx.abs(), gy.abs()
    vertical = ay <= _TAN * ax
    horizontal = ~vertical & (ax <= _TAN * ay)
    rising = ~vertical & ~horizontal & (gx * gy > 0)
    falling = ~vertical & ~horizontal & ~rising
    zero = torch.zeros_like(mag)
    bins = torch.stack([torch.where(m, mag, zero) for m in (vertical, rising, horizontal, falling)], -1)
    ii = torch.zeros(b, h + 1, w + 1, 4, dtype=torch.float64, device=grey.device)
    ii[:, 1:, 1:] = bins.cumsum(2).cumsum(1)
    return ii


@numba.njit(cache=True, nogil=True)
def _integrals_kernel(g: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`orientation_integrals` of ``g`` ``float32 (B, h, w)`` into ``out``: per pixel
    the tensor path's Sobel, magnitude and bin; each row's running sums added to the row above's."""
    nb, h, w = g.shape
    tan = np.tan(np.pi / 8)
    for b in range(nb):
        out[b, 0].fill(0.0)
        for y in range(h):
            gu, gm, gd = g[b, max(y - 1, 0)], g[b, y], g[b, min(y + 1, h - 1)]
            above, row = out[b, y], out[b, y + 1]
            row[0].fill(0.0)
            r0 = r1 = r2 = r3 = 0.0
            # the 3 × 3 neighbourhood slides along the row: one new column a pixel
            uc, ur, mc, mr, dc, dr = float(gu[0]), float(gu[0]), float(gm[0]), float(gm[0]), float(gd[0]), float(gd[0])
            for x in range(w):
                xr = min(x + 1, w - 1)
                ul, uc, ur = uc, ur, float(gu[xr])
                ml, mc, mr = mc, mr, float(gm[xr])
                dl, dc, dr = dc, dr, float(gd[xr])
                gx = (ur + 2.0 * mr + dr - ul - 2.0 * ml - dl) * 0.125  # = / 8, exactly
                gy = (dl + 2.0 * dc + dr - ul - 2.0 * uc - ur) * 0.125
                mag = np.sqrt(gx * gx + gy * gy)
                ax, ay = abs(gx), abs(gy)
                # without branches (a pixel's bin is a coin toss where the gradient is faint):
                # mag · 1 or mag · 0 added, the same sums as the tensor path's zeros
                m0 = 1.0 if ay <= tan * ax else 0.0
                m2 = (1.0 - m0) * (1.0 if ax <= tan * ay else 0.0)
                m1 = (1.0 - m0 - m2) * (1.0 if gx * gy > 0 else 0.0)
                m3 = 1.0 - m0 - m2 - m1
                r0 += mag * m0
                r1 += mag * m1
                r2 += mag * m2
                r3 += mag * m3
                a, o = above[x + 1], row[x + 1]
                o[0], o[1], o[2], o[3] = a[0] + r0, a[1] + r1, a[2] + r2, a[3] + r3


def _sums(ii: Tensor, bi: Tensor, x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor) -> Tensor:
    """Each bin's sum over the boxes ``[x0, x1) × [y0, y1)`` of images ``bi``: ``float64 [K, 4]``."""
    return ii[bi, y1, x1] - ii[bi, y0, x1] - ii[bi, y1, x0] + ii[bi, y0, x0]


def orientation_features(ii: Tensor, boxes: Tensor, bi: Tensor, out: Tensor | None = None) -> Tensor:
    """The columns :data:`ORIENTATION_NAMES` of ``int64 [K, 4]`` working-pixel boxes
    ``(x0, y0, x1, y1)`` (ends exclusive) of images ``bi`` ``int64 [K]``, from
    :func:`orientation_integrals`' ``ii``: ``float32 [K, 8]``, each bin's share of the
    gradient energy inside the box (4), then in its inner border band (4); on the CPU
    written into ``out`` (``float32 [K, 8]``, a view such as the last columns of the
    features) where given."""
    if ii.device.type == "cpu":
        res = torch.empty(len(boxes), 8) if out is None else out
        t, bx, b, o = ii.numpy(), boxes.contiguous().numpy(), bi.contiguous().numpy(), res.numpy()
        on_two_cores(lambda lo, hi: _features_kernel(t, bx, b, o, lo, hi), len(boxes))
        return res
    return _features_tensor(ii, boxes, bi)


def _features_tensor(ii: Tensor, boxes: Tensor, bi: Tensor) -> Tensor:
    """:func:`orientation_features` as tensor ops (any device)."""
    h, w = ii.shape[1] - 1, ii.shape[2] - 1
    x0, y0, x1, y1 = boxes.unbind(1)
    ix0, iy0, ix1, iy1 = _grown(x0, y0, x1, y1, -BORDER, h, w)
    inside = _sums(ii, bi, x0, y0, x1, y1)
    band = (inside - _sums(ii, bi, ix0, iy0, ix1, iy1)).clamp(min=0)  # rounding, not energy, below 0
    inside = inside.clamp(min=0)
    return torch.cat([inside / (inside.sum(1, keepdim=True) + _EPS),
                      band / (band.sum(1, keepdim=True) + _EPS)], 1).float()


@numba.njit(cache=True, nogil=True)
def _features_kernel(ii: np.ndarray, boxes: np.ndarray, bi: np.ndarray, out: np.ndarray, lo: int,
                     hi: int) -> None:  # pragma: no cover - compiled
    """Rows ``lo:hi`` of :func:`orientation_features` (the tensor path's arithmetic)."""
    h, w = ii.shape[1] - 1, ii.shape[2] - 1
    s_in = np.empty(4)
    s_band = np.empty(4)
    for k in range(lo, hi):
        b = bi[k]
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        ix0, ix1 = _grow(x0, x1, -BORDER, 0, w)  # the inner box, as the features' border band
        iy0, iy1 = _grow(y0, y1, -BORDER, 0, h)
        t_in, t_band = 0.0, 0.0
        for j in range(4):
            a = ii[b, y1, x1, j] - ii[b, y0, x1, j] - ii[b, y1, x0, j] + ii[b, y0, x0, j]
            c = ii[b, iy1, ix1, j] - ii[b, iy0, ix1, j] - ii[b, iy1, ix0, j] + ii[b, iy0, ix0, j]
            s_band[j] = max(a - c, 0.0)
            s_in[j] = max(a, 0.0)
        for j in range(4):  # the tensor path's sum(1): left to right
            t_in += s_in[j]
            t_band += s_band[j]
        for j in range(4):
            out[k, j] = s_in[j] / (t_in + _EPS)
            out[k, 4 + j] = s_band[j] / (t_band + _EPS)
