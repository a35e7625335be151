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
from functools import cached_property, lru_cache

import torch
from torch import Tensor

__all__ = ["WindowSize", "WindowGrid", "window_sizes", "camera_window_sizes", "window_grid"]


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

    @cached_property
    def min_side(self) -> int:
        """The smallest width or height of any size (working pixels; 0 without sizes)."""
        return min((min(s.w, s.h) for s in self.sizes), default=0)


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


def _merge(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for lo, hi in sorted(intervals):
        if out and lo <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], hi))
        else:
            out.append((lo, hi))
    return out


def camera_window_sizes(height: int, width: int, min_window: int, ratio: float, step: float,
                        horizon: float, templates: tuple[tuple[float, float, float, float], ...]) -> list[WindowSize]:
    """Window sizes and rows derived from the ground plane and class templates (working pixels).

    A camera at height ``h_c`` above a flat road, looking along it, sees an object of real
    height ``H`` and width ``W`` (metres) standing at depth ``Z`` with its bottom row
    ``y_b = y_h + f·h_c/Z`` (``y_h``: the horizon row) and a box of ``f·H/Z × f·W/Z`` pixels:

        box height / (y_b − y_h) = H / h_c,    box width / (y_b − y_h) = W / h_c,

    whatever the focal length (the paper's eqs. 5–7 carried through to the windows, and how
    Mono3D / 3DOP place their candidates). ``templates`` holds, per class, the ranges of
    those two ratios ``(h_lo, h_hi, w_lo, w_hi)`` (real extents divided by the camera
    height). A ``w × h`` window is kept at the rows whose depth ``d = y_b − y_h`` fits a
    template in both height and width: ``d ∈ [max(h/h_hi, w/w_hi), min(h/h_lo, w/w_lo)]``,
    one :class:`WindowSize` per band of rows (the union over templates).

    Windows flush with the left or right image border are added at every
    width down to ``min_window`` (height still from the templates): objects cut by the image
    border keep their height but not their width. Such a size has ``sx = width − w``, so its
    two columns are ``x0 = 0`` and ``x0 = width − w``.

    Sizes run over geometric series from ``min_window`` (ratio ``ratio``) up to the image
    height and width; strides are ``max(1, round(step·side))``.
    """
    yh = horizon * height
    out: list[WindowSize] = []
    widths = _series(min_window, width, ratio)
    heights = _series(min_window, height, ratio)

    def rows(h: int, sy: int, lo: float, hi: float) -> tuple[int, int] | None:
        j_lo = max(0, math.ceil((yh + lo - h) / sy - 1e-9))
        j_hi = min((height - h) // sy, math.floor((yh + hi - h) / sy + 1e-9))
        return (j_lo, j_hi) if j_hi >= j_lo else None

    for w in widths:
        for h in heights:
            sx, sy = max(1, round(step * w)), max(1, round(step * h))
            full = _merge([(max(h / hh, w / wh), min(h / hl, w / wl)) for hl, hh, wl, wh in templates
                           if max(h / hh, w / wh) <= min(h / hl, w / wl)])
            for lo, hi in full:
                r = rows(h, sy, lo, hi)
                if r is not None:
                    out.append(WindowSize(w, h, sx, sy, (width - w) // sx + 1, r[1] - r[0] + 1, r[0] * sy))
            if w >= width:
                continue
            # cut by the image border: the width may be anything up to the template's
            cut = _merge([(max(h / hh, w / wh), h / hl) for hl, hh, wl, wh in templates
                          if max(h / hh, w / wh) <= h / hl])
            for lo, hi in cut:
                # leave out the rows the full-width windows already cover at the border
                for a, b in _subtract((lo, hi), full):
                    r = rows(h, sy, a, b)
                    if r is not None:
                        out.append(WindowSize(w, h, width - w, sy, 2, r[1] - r[0] + 1, r[0] * sy))
    return out


def _subtract(iv: tuple[float, float], minus: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Parts of interval ``iv`` outside the (sorted, disjoint) intervals ``minus``."""
    parts = [iv]
    for a, b in minus:
        nxt = []
        for lo, hi in parts:
            if b < lo or a > hi:
                nxt.append((lo, hi))
                continue
            if lo < a:
                nxt.append((lo, a - 1e-6))
            if b < hi:
                nxt.append((b + 1e-6, hi))
        parts = nxt
    return parts


@lru_cache(maxsize=32)
def _grid(height: int, width: int, bounds: tuple[tuple[int, int], ...], min_window: int, ratio: float,
          step: float, aspect: tuple[float, float], assign: str,
          ground: tuple[float, float, float] | None,
          camera: tuple | None = None) -> WindowGrid:
    if camera is not None:
        horizon, templates = camera
        sizes = camera_window_sizes(height, width, min_window, ratio, step, horizon, templates)
    else:
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
                ground: tuple[float, float, float] | None = None,
                camera: tuple[float, tuple[tuple[float, float, float, float], ...]] | None = None,
                ) -> WindowGrid:
    """The (cached) :class:`WindowGrid` of a ``height × width`` working image whose
    regions have column ``bounds`` (``int64 [R, 2]``); ``min_window`` in working pixels;
    ``ground`` as in :func:`window_sizes`. With ``camera = (horizon, templates)``
    the sizes come from :func:`camera_window_sizes` instead (``aspect`` and ``ground`` are
    then unused, and a window may be wider than its region: regions only set budgets)."""
    key = tuple((int(a), int(b)) for a, b in bounds.tolist())
    g = None if ground is None else tuple(float(v) for v in ground)
    cam = None
    if camera is not None:
        cam = (float(camera[0]), tuple(tuple(float(v) for v in t) for t in camera[1]))
    return _grid(height, width, key, int(min_window), float(ratio), float(step), tuple(aspect), assign, g, cam)
