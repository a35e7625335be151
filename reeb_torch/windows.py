"""Sec. 3.6 — dense sliding windows, and the region each window counts against.

Window sizes are a grid of widths × heights, each a geometric series from
``min_window`` with ratio ``size_ratio``, kept when width/height lies in
``aspect_range``; the widest window is within one ratio of the region's width (the whole image without
region enhancement). A window of size ``w × h`` slides with strides
``max(1, round(step·w))`` and ``max(1, round(step·h))`` from the top-left corner.
Everything here depends only on the image size and the config, so it is cached.

Coordinates are working-resolution pixels; a window at column ``x0`` covering ``w``
pixels is the box ``(x0, y0, x0 + w, y0 + h)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor

__all__ = ["WindowSize", "WindowGrid", "window_sizes", "window_grid"]


@dataclass(frozen=True)
class WindowSize:
    """One window size and its position grid: positions ``x0 = i·sx`` (``i < nx``),
    ``y0 = oy + j·sy`` (``j < ny``)."""

    w: int
    h: int
    sx: int
    sy: int
    nx: int
    ny: int
    oy: int = 0

    @property
    def count(self) -> int:
        return self.nx * self.ny


@dataclass
class WindowGrid:
    """All windows of one image size.

    Attributes:
        sizes: the ``S`` window sizes, in scoring order.
        offsets: ``S + 1`` start indices of each size in the flat window list.
        boxes: ``float32 [N, 4]`` all windows (x1, y1, x2, y2), working pixels, flat order
            (size-major, then row-major positions).
        region_windows: per region, ``int64`` indices of the windows that count against it.
        region_of: ``int64 [N]`` the region whose centre is nearest to each window's centre.
    """

    sizes: list[WindowSize]
    offsets: list[int]
    boxes: Tensor
    region_windows: list[Tensor]
    region_of: Tensor

    @property
    def count(self) -> int:
        return self.offsets[-1]


def _series(lo: float, hi: float, ratio: float) -> list[int]:
    out: list[int] = []
    v = lo
    while round(v) <= hi:
        r = int(round(v))
        if not out or r != out[-1]:
            out.append(r)
        v *= ratio
    if out and hi - out[-1] > 0.5 * (out[-1] * ratio - out[-1]):
        out.append(int(hi))  # reach the largest allowed size
    return out


def window_sizes(height: int, width: int, max_width: int, min_window: int, ratio: float,
                 step: float, aspect: tuple[float, float],
                 ground: tuple[float, float, float] | None = None) -> list[WindowSize]:
    """The window sizes and strides for a ``height × width`` image (working pixels).

    ``ground = (horizon, r_lo, r_hi)`` keeps, for each height ``h``, only the rows whose
    bottom ``y_b`` makes ``h / (y_b − horizon·height)`` lie in ``[r_lo, r_hi]``: an
    object standing on a flat road has a box height about proportional to how far below
    the horizon its bottom is (object height / camera height).
    """
    out = []
    widths = _series(min_window, min(max_width, width), ratio)
    heights = _series(min_window, height, ratio)
    for w in widths:
        for h in heights:
            if not (aspect[0] <= w / h <= aspect[1]):
                continue
            sx, sy = max(1, round(step * w)), max(1, round(step * h))
            j_lo, j_hi = 0, (height - h) // sy
            if ground is not None:
                yh, r_lo, r_hi = ground[0] * height, ground[1], ground[2]
                j_lo = max(j_lo, math.ceil((yh + h / r_hi - h) / sy - 1e-9))
                j_hi = min(j_hi, math.floor((yh + h / r_lo - h) / sy + 1e-9))
                if j_hi < j_lo:
                    continue
            out.append(WindowSize(w, h, sx, sy, (width - w) // sx + 1, j_hi - j_lo + 1, j_lo * sy))
    return out


@lru_cache(maxsize=32)
def _grid(height: int, width: int, bounds: tuple[tuple[int, int], ...], min_window: int, ratio: float,
          step: float, aspect: tuple[float, float], assign: str,
          ground: tuple[float, float, float] | None) -> WindowGrid:
    region_w = max(b - a for a, b in bounds)
    sizes = window_sizes(height, width, region_w, min_window, ratio, step, aspect, ground)
    boxes, offsets = [], [0]
    for s in sizes:
        xs = torch.arange(s.nx, dtype=torch.float32) * s.sx
        ys = torch.arange(s.ny, dtype=torch.float32) * s.sy + s.oy
        y0, x0 = torch.meshgrid(ys, xs, indexing="ij")
        boxes.append(torch.stack([x0, y0, x0 + s.w, y0 + s.h], -1).view(-1, 4))
        offsets.append(offsets[-1] + s.count)
    allb = torch.cat(boxes) if boxes else torch.zeros(0, 4)
    b = torch.tensor(bounds, dtype=torch.float32)  # (R, 2)
    centre = (allb[:, 0] + allb[:, 2]) / 2
    nearest = (centre[:, None] - b.mean(1)[None]).abs().argmin(1)
    if assign == "contained":
        inside = (allb[:, None, 0] >= b[None, :, 0]) & (allb[:, None, 2] <= b[None, :, 1])  # (N, R)
        region_windows = [torch.nonzero(inside[:, r]).squeeze(1) for r in range(len(bounds))]
    else:
        region_windows = [torch.nonzero(nearest == r).squeeze(1) for r in range(len(bounds))]
    return WindowGrid(sizes, offsets, allb, region_windows, nearest)


def window_grid(height: int, width: int, bounds: Tensor, min_window: int, ratio: float, step: float,
                aspect: tuple[float, float], assign: str = "nearest",
                ground: tuple[float, float, float] | None = None) -> WindowGrid:
    """The (cached) :class:`WindowGrid` of a ``height × width`` working image whose
    regions have column ``bounds`` (``int64 [R, 2]``); ``min_window`` in working pixels;
    ``ground`` as in :func:`window_sizes`."""
    key = tuple((int(a), int(b)) for a, b in bounds.tolist())
    g = None if ground is None else tuple(float(v) for v in ground)
    return _grid(height, width, key, int(min_window), float(ratio), float(step), tuple(aspect), assign, g)
