"""Sec. 3.7 — scoring every sliding window: edge score S (eq. 1), road score R (eq. 10),
location score L (eq. 11), their combination V (eq. 12), and the shadow term (not in the
paper; :func:`shadow_fraction`).

On the CPU, :func:`score_grid_cpu` scores every window of every size in one compiled
(numba) pass, with the same arithmetic as the tensor ops below. The tensor path (any
device, any config) scores each window size for all its positions and all images at once:

* the centre term Σ_c m_c and R are box sums read from integral images at strided
  positions (four strided slices, no gather);
* the wholly-enclosed term Σ_n w_n m_n is exact: for windows of one size, the positions
  that wholly contain a group's bounding box form a rectangle ``[i0, i1] × [j0, j1]`` in
  position space, so the group adds its magnitude to that rectangle with four
  scatter-adds into a difference array; two cumulative sums then give every window's
  enclosed mass. All sizes share one scatter (``index_add_``) into one flat buffer.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from . import _scratch
from ._radix import kth_largest
from ._threads import images_or_rows, on_two_cores
from .groups import EdgeGroups
from .windows import WindowSize

__all__ = [
    "integral_image",
    "count_integral",
    "box_sums",
    "enclosed_sums",
    "edge_score",
    "location_score",
    "combined_score",
    "score_grid_cpu",
    "row_order",
    "shadow_strips",
    "shadow_fraction",
    "apply_shadow",
    "vegetation_factor",
]

def integral_image(x: Tensor, key: str | None = None) -> Tensor:
    """``(B, H, W)`` → ``float64 (B, H + 1, W + 1)`` with ``ii[:, y, x] = Σ x[:, :y, :x]``.

    float64 holds the sums of float32 edge magnitudes exactly (an image's whole edge mass
    needs well under 53 bits), so box sums do not depend on summation order or batch.

    On the CPU (float32 input) one compiled pass (numba) per half batch fills the table,
    summing in the order of the tensor ops (along rows, then down columns): the same
    numbers (tested equal) without the float64 copy and the two intermediate tables; with
    a ``key``, in a buffer a generator's ``forward`` reuses (:mod:`._scratch`)."""
    b, h, w = x.shape
    if x.device.type == "cpu" and x.dtype == torch.float32 and not x.requires_grad:
        src = x.contiguous().numpy()
        out = np.empty((b, h + 1, w + 1)) if key is None else _scratch.empty(key, (b, h + 1, w + 1))
        on_two_cores(lambda lo, hi: _integral_kernel(src[lo:hi], out[lo:hi]), b)
        return torch.from_numpy(out)
    ii = torch.zeros(b, h + 1, w + 1, dtype=torch.float64, device=x.device)
    ii[:, 1:, 1:] = x.to(torch.float64).cumsum(2).cumsum(1)
    return ii


def count_integral(mask: Tensor) -> Tensor:
    """``(B, H, W)`` 0/1 mask → ``int32 (B, H + 1, W + 1)`` with ``c[:, y, x]`` the number of
    set pixels in ``mask[:, :y, :x]`` (half the memory of :func:`integral_image`'s
    float64, and the same numbers: counts are exact either way). CPU; elsewhere
    :func:`integral_image`."""
    if mask.device.type != "cpu":
        return integral_image(mask)
    src = (mask != 0).contiguous().numpy()
    b, h, w = src.shape
    out = np.empty((b, h + 1, w + 1), np.int32)
    on_two_cores(lambda lo, hi: _integral_kernel(src[lo:hi], out[lo:hi]), b)
    return torch.from_numpy(out)


@numba.njit(cache=True, nogil=True)
def _integral_kernel(x: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`integral_image` of ``x`` ``float32 (B, H, W)`` into ``out`` ``float64
    (B, H + 1, W + 1)`` (or :func:`count_integral` of a bool ``x`` into ``int32``): each
    row's running sum, in ``out``'s type, added to the row above's table entry.

    Four rows at a time: a row's running sum is a chain of dependent float64 additions
    (one per pixel, each waiting for the last), and four independent chains side by side
    keep the core busy; every entry is the same two additions as row by row (timed with
    ``benchmarks/kernel_ab.py``; docs/results.md, "What makes the CPU path fast")."""
    nb, h, w = x.shape
    for b in range(nb):
        out[b, 0].fill(0)
        i = 0
        while i + 4 <= h:
            for k in range(1, 5):
                out[b, i + k, 0] = 0
            r0 = r1 = r2 = r3 = out[b, i + 1, 0]  # 0 in out's type
            x0, x1, x2, x3 = x[b, i], x[b, i + 1], x[b, i + 2], x[b, i + 3]
            above, o0, o1, o2, o3 = out[b, i], out[b, i + 1], out[b, i + 2], out[b, i + 3], out[b, i + 4]
            for j in range(w):
                r0 += x0[j]
                r1 += x1[j]
                r2 += x2[j]
                r3 += x3[j]
                v = above[j + 1] + r0
                o0[j + 1] = v
                v = v + r1
                o1[j + 1] = v
                v = v + r2
                o2[j + 1] = v
                o3[j + 1] = v + r3
            i += 4
        for i in range(i, h):  # the last rows (fewer than four)
            out[b, i + 1, 0] = 0
            run = out[b, i + 1, 0]  # 0 in out's type
            for j in range(w):
                run += x[b, i, j]
                out[b, i + 1, j + 1] = out[b, i, j + 1] + run


def extend_below(ii: Tensor) -> Tensor:
    """An integral image ``(B, H + 1, W + 1)`` extended by ``H`` rows that repeat its last
    row, ``(B, 2H + 1, W + 1)``: box sums that reach past the image bottom count the rows
    past it as zeros (for the strips just below a box)."""
    return torch.cat([ii, ii[:, -1:].expand(-1, ii.shape[1] - 1, -1)], 1)


def box_sums(ii: Tensor, dx: int, dy: int, bw: int, bh: int, s: WindowSize) -> Tensor:
    """Sums of the ``bw × bh`` boxes at ``(i·sx + dx, oy + j·sy + dy)`` for all positions
    of ``s``: ``(B, ny, nx)`` from an integral image ``(B, H + 1, W + 1)``."""

    def at(oy: int, ox: int) -> Tensor:
        return ii[:, oy: oy + (s.ny - 1) * s.sy + 1: s.sy, ox: ox + (s.nx - 1) * s.sx + 1: s.sx]

    dy += s.oy
    return at(dy + bh, dx + bw) - at(dy, dx + bw) - at(dy + bh, dx) + at(dy, dx)


def enclosed_sums(groups: EdgeGroups, batch: int, sizes: list[WindowSize]) -> list[Tensor]:
    """Σ_n w_n·m_n of eq. 1 for every window: the magnitude of the groups whose bounding
    box lies wholly inside the window (window pixels ``[x0, x0 + w)``, group pixels
    ``[x1, x2]``: enclosed iff ``x0 <= x1`` and ``x2 < x0 + w``, same for y; window
    positions ``x0 = i·sx``, ``y0 = oy + j·sy``).

    For one size, the positions whose window encloses a group form the rectangle
    ``i0 = ceil((x2 + 1 − w)/sx) <= i <= i1 = floor(x1/sx)`` (same for j), so each group
    adds its magnitude at four corners of a difference array and two cumulative sums give
    all windows at once. Only the groups inside the size's band of rows are visited
    (groups sorted by top row, ``searchsorted``).

    Returns one ``float64 (B, ny, nx)`` tensor per size (exact: float64 sums of the groups'
    float64 masses, so the same whatever the order of the scatter or the batch).
    """
    dev = groups.batch.device
    order = torch.sort(groups.y1, stable=True).indices  # stable: same sums alone or in a batch
    gy1 = groups.y1[order]
    gx1, gx2, gy2 = groups.x1[order], groups.x2[order], groups.y2[order]
    gb, gm = groups.batch[order], groups.magnitude[order].to(torch.float64)  # exact sums, any order
    if sizes:
        top = torch.tensor([s.oy for s in sizes], device=dev)
        bottom = torch.tensor([s.oy + (s.ny - 1) * s.sy + s.h - 1 for s in sizes], device=dev)
        los = torch.searchsorted(gy1, top).tolist()
        his = torch.searchsorted(gy1, bottom, right=True).tolist()
    out = []
    for k, s in enumerate(sizes):
        row = s.nx + 1
        buf = torch.zeros(batch * (s.ny + 1) * row, dtype=torch.float64, device=dev)
        lo, hi = los[k], his[k]
        if hi > lo:
            x1, x2, y1, y2 = gx1[lo:hi], gx2[lo:hi], gy1[lo:hi], gy2[lo:hi]
            i0 = torch.div(x2 + (s.sx - s.w), s.sx, rounding_mode="floor").clamp_(min=0)  # ceil((x2+1-w)/sx)
            i1 = torch.div(x1, s.sx, rounding_mode="floor").clamp_(max=s.nx - 1)
            j0 = torch.div(y2 + (s.sy - s.h - s.oy), s.sy, rounding_mode="floor").clamp_(min=0)
            j1 = torch.div(y1 - s.oy, s.sy, rounding_mode="floor").clamp_(max=s.ny - 1)
            ok = torch.nonzero((i0 <= i1) & (j0 <= j1)).squeeze(1)
            if ok.numel():
                i0, i1, j0, j1 = i0[ok], i1[ok] + 1, j0[ok] * row, (j1[ok] + 1) * row
                base = gb[lo:hi][ok] * ((s.ny + 1) * row)
                m = gm[lo:hi][ok]
                idx = torch.cat([base + j0 + i0, base + j0 + i1, base + j1 + i0, base + j1 + i1])
                buf.index_add_(0, idx, torch.cat([m, -m, -m, m]))
        d = buf.view(batch, s.ny + 1, row)
        out.append(d.cumsum(2).cumsum(1)[:, : s.ny, : s.nx])
    return out


def edge_score(enclosed: Tensor, centre: Tensor, w: float | Tensor, h: float | Tensor, norm: str, kappa: float,
               gamma: float) -> Tensor:
    """Eq. 1: S = (Σ_n w_n m_n − Σ_c m_c) / normaliser, with ``w``, ``h`` the window's size
    in the units the sums are in. ``perimeter``: (2(w + h))^κ (Edge Boxes);
    ``area``: 2·(w·h)^γ (as printed)."""
    return (enclosed - centre) / edge_norm(w, h, norm, kappa, gamma)


def edge_norm(w, h, norm: str, kappa: float, gamma: float):
    """Eq. 1's normaliser of a ``w × h`` window (floats or tensors): ``perimeter``:
    (2(w + h))^κ; ``area``: 2·(w·h)^γ."""
    return (2.0 * (w + h)) ** kappa if norm == "perimeter" else 2.0 * (w * h) ** gamma


def location_score(bottom: Tensor, bw: float | Tensor, bh: float | Tensor, img_w: float, img_h: float, mode: str,
                   horizon: float = 0.47, ratios: tuple[float, ...] = (1.0,), log_sigma: float = 0.5,
                   weights: tuple[float, ...] | None = None,
                   widths: tuple[tuple[float, float], ...] | None = None, camera_height: float = 1.0) -> Tensor:
    """Eq. 11 and variants, for boxes of size ``bw × bh`` whose bottom rows are ``bottom``
    (input pixels, from the image top).

    ``paper``: L = b_y / (b_w·b_h) · image width (unbounded). ``classes``: for each object
    class a Gaussian in log(b_h / (b_y − horizon·H) / ratio), 0 above the horizon, in
    [0, 1], with one ``ratios`` entry per class, taking the best fitting class, each class's
    Gaussian scaled by its ``weights`` (a max-mixture over the class templates): the product
    of :func:`class_height_fits` and, with ``widths``, :func:`class_width_fits`. ``none``: 1.
    """
    if mode == "paper":
        return bottom * (img_w / (bw * bh))
    if mode == "classes":
        fits = class_height_fits(bottom, bh, img_h, horizon, ratios, log_sigma, weights)
        if widths is not None:
            fits = [f * g for f, g in zip(fits, class_width_fits(bottom, bw, img_h, horizon, widths, log_sigma,
                                                                 camera_height))]
        val = fits[0]
        for f in fits[1:]:
            val = torch.maximum(val, f)
        return val
    return torch.ones_like(bottom)


def class_height_fits(bottom: Tensor, bh: float | Tensor, img_h: float, horizon: float, ratios: tuple[float, ...],
                      log_sigma: float, weights: tuple[float, ...] | None = None) -> list[Tensor]:
    """How well a box ``bh`` tall standing at row ``bottom`` (input pixels) fits each class:
    ``w_c · exp(−(log(b_h / (b_y − horizon·H)) − log r_c)² / 2σ²)`` for each ratio r_c
    (class height / camera height) and weight w_c, 0 where the bottom is not below the
    horizon; one tensor per class, broadcast over ``bottom`` and ``bh``."""
    depth = bottom - horizon * img_h
    log_r = torch.log(bh / depth.clamp_min(1e-6))
    weights = (1.0,) * len(ratios) if weights is None else weights
    above = depth <= 0
    return [torch.where(above, 0.0, wc * torch.exp(-((log_r - math.log(c)) ** 2) / (2 * log_sigma**2)))
            for c, wc in zip(ratios, weights)]


def class_width_fits(bottom: Tensor, bw: float | Tensor, img_h: float, horizon: float,
                     widths: tuple[tuple[float, float], ...], log_sigma: float, camera_height: float) -> list[Tensor]:
    """How well a box ``bw`` wide standing at row ``bottom`` (input pixels) fits each class's
    width range ``(lo, hi)`` in metres (``ReebConfig.object_templates``): the box's
    width on the road at that depth, ``b_w · camera_height / (b_y − horizon·H)`` (square
    pixels), is 1 inside the range and falls off as a Gaussian of its log distance from the
    range with the height fit's tolerance ``log_sigma``; one tensor per class."""
    depth = bottom - horizon * img_h
    log_w = torch.log(bw * camera_height / depth.clamp_min(1e-6))
    out = []
    for lo, hi in widths:
        off = (math.log(lo) - log_w).clamp_min(0.0) + (log_w - math.log(hi)).clamp_min(0.0)
        out.append(torch.exp(-(off**2) / (2 * log_sigma**2)))
    return out


def combined_score(s: Tensor, loc: Tensor, road: Tensor, alpha: float, beta: float, road_mode: str) -> Tensor:
    """Eq. 12: V = S·(α·L + β·R) (``reward``); ``none`` drops the road term."""
    if road_mode == "none":
        road = torch.zeros_like(road)
    return s * (alpha * loc + beta * road)


def centre_box(w: int, h: int, fraction: float) -> tuple[int, int, int, int]:
    """Offset and size ``(dx, dy, cw, ch)`` of the centre region c of a ``w × h`` window
    (eq. 1: half its width and height, centred)."""
    cw, ch = max(1, int(round(w * fraction))), max(1, int(round(h * fraction)))
    return (w - cw) // 2, (h - ch) // 2, cw, ch


def unit_scale(scale_x: float, scale_y: float) -> float:
    """Factor turning a sum of edge magnitudes along a working-resolution contour into
    input pixels (contours are 1-D, so lengths scale with the mean factor)."""
    return 2.0 / (scale_x + scale_y) if math.isfinite(scale_x + scale_y) else 1.0


# ---------------------------------------------------------------------------------------
# compiled CPU path: every window of every size in one pass
# ---------------------------------------------------------------------------------------
PLAN_COLUMNS = ("w", "h", "sx", "sy", "nx", "ny", "oy", "offset", "dx", "dy", "cw", "ch", "loc_offset",
                "shadow_rows", "shadow_margin", "green_dx", "green_dy", "green_w", "green_h")
"""Columns of the ``int64 [S, 19]`` size table :func:`score_grid_cpu` reads, one row per size."""


@numba.njit(cache=True, nogil=True, inline="always")  # one function to the compiler
def _row_edge_scores(e0, e1, a0, a1, c0, c1, r1, k1, nx: int, sx: int, w: int, dx: int, cw: int, unit: float,
                     d: float, num: np.ndarray, val: np.ndarray) -> None:  # pragma: no cover - compiled
    """S (eq. 1) of one row of ``nx`` windows into ``val``: the table rows at the window's
    top and bottom (edge integral ``e``, enclosed-sum tables ``a``, ``c``, ``r``, ``k``) read
    into ``num`` first, then divided (a loop the compiler vectorises)."""
    usx, uw, udx, ucw = np.uint64(sx), np.uint64(w), np.uint64(dx), np.uint64(cw)
    for i in range(nx):
        x0 = np.uint64(i) * usx  # unsigned: no test for negative indices on each of the 13 loads
        x1 = x0 + uw
        cx0 = x0 + udx
        cx1 = cx0 + ucw
        centre = ((e1[cx1] - e0[cx1]) - e1[cx0]) + e0[cx0]
        a = ((a1[x1] - a0[x1]) - a1[x0]) + a0[x0]
        col = c1[x1] - c0[x1]
        rw = r1[x1] - r1[x0]
        enc = ((a - col) - rw) + k1[x1]
        num[i] = enc * unit - centre * unit
    for i in range(nx):
        val[i] = np.float32(num[i] / d)


@numba.njit(cache=True, nogil=True, inline="always")  # one function to the compiler
def _row_vegetation(g0, g1, nx: int, sx: int, gdx: int, gw: int, inv_area: float, veg_power: int,
                    fac: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`vegetation_factor` of one row of windows into ``fac`` (green counts ``g``)."""
    usx, ugdx, ugw = np.uint64(sx), np.uint64(gdx), np.uint64(gw)
    for i in range(nx):
        gx0 = np.uint64(i) * usx + ugdx  # unsigned, as in _row_edge_scores
        gx1 = gx0 + ugw
        gs = ((g1[gx1] - g0[gx1]) - g1[gx0]) + g0[gx0]
        q = 1.0 - float(gs) * inv_area
        f = q
        for _ in range(veg_power - 1):
            f = f * q
        fac[i] = np.float32(f)


@numba.njit(cache=True, nogil=True, inline="always")  # one function to the compiler
def _row_shadow(q0, q1, q2, nx: int, sx: int, w: int, mx: int, below: bool, n_in: float, n_below: float,
                sqrt_floor: float, s_in: np.ndarray, s_below: np.ndarray, val: np.ndarray, ob: np.ndarray,
                us: np.ndarray, row: int) -> None:  # pragma: no cover - compiled
    """The shadow term of one row of windows (grey integral rows ``q0``, ``q1``, ``q2`` at
    the strip's top, the box bottom and the strip below's bottom; ``below``: a row lies
    below the box): with ``sqrt_floor >= 0`` V (``val``, ``-inf`` stays) times
    sqrt(U + floor) into ``ob[row:]``, else V into ``ob[row:]`` and U into ``us[row:]``."""
    neg_inf = np.float32(-np.inf)
    o = ob[row: row + nx]  # indexed from 0 (no test for negative indices: loops that vectorise)
    usx, umx, uax = np.uint64(sx), np.uint64(mx), np.uint64(w - mx)
    for i in range(nx):
        ax0 = np.uint64(i) * usx + umx  # unsigned, as in _row_edge_scores
        ax1 = np.uint64(i) * usx + uax
        s_in[i] = ((q1[ax1] - q0[ax1]) - q1[ax0]) + q0[ax0]
        s_below[i] = ((q2[ax1] - q1[ax1]) - q2[ax0]) + q1[ax0]
    if sqrt_floor < 0:  # U for apply_shadow
        ou = us[row: row + nx]
        for i in range(nx):
            o[i] = val[i]
            u = 0.0
            if below:
                g_in = s_in[i] / n_in
                g_below = s_below[i] / n_below
                u = min(max((g_below - g_in) / max(g_below, 1e-3), 0.0), 1.0)
            ou[i] = u
    elif below:
        for i in range(nx):
            g_in = s_in[i] / n_in
            g_below = s_below[i] / n_below
            t = (g_below - g_in) / (g_below if g_below > 1e-3 else 1e-3)
            t = t if t > 0.0 else 0.0
            t = t if t < 1.0 else 1.0
            v = val[i]
            o[i] = v * np.float32(np.sqrt(t + sqrt_floor)) if v != neg_inf else neg_inf
    else:  # no row below the box: U = 0
        f0 = np.float32(np.sqrt(0.0 + sqrt_floor))
        for i in range(nx):
            v = val[i]
            o[i] = v * f0 if v != neg_inf else neg_inf


@numba.njit(cache=True, nogil=True)
def _score_grid_kernel(ii: np.ndarray, anchor: np.ndarray, cut_col: np.ndarray, cut_row: np.ndarray,
                       corner: np.ndarray, plan: np.ndarray, order: np.ndarray, denom: np.ndarray, loc: np.ndarray,
                       unit: float, alpha: np.float32, beta_r: np.float32, min_edge: np.float32,
                       out: np.ndarray, grey: np.ndarray, shadow: np.ndarray,
                       sqrt_floor: float, green: np.ndarray, veg_power: int) -> None:  # pragma: no cover - compiled
    """V of every window (the torch path's arithmetic, operation for operation, so the same
    float32 numbers): eq. 1 from the edge integral image and the enclosed-sum prefix
    tables, times ``alpha·L + beta_r`` (``beta_r`` = β·R for a constant R). With a grey
    integral image (``grey.shape[0] > 0``), also U of :func:`shadow_fraction`: into ``shadow``,
    or, with ``sqrt_floor >= 0`` (a power of 0.5), straight into V as :func:`apply_shadow`
    does it (sqrt is correctly rounded in both, so the numbers are the same). With a green
    integral image (``green.shape[0] > 0``), V is first multiplied by
    :func:`vegetation_factor`.

    One row of windows (a size, a window row) at a time, the rows of ``order`` (``int64
    [M, 2]``: size, row; :func:`row_order`) in turn, in passes over the row: the table
    reads (strided gathers) into short buffers, then the divisions, square roots and
    products over those buffers, which the compiler vectorises; each window's numbers are
    the same operations in the same order as one window at a time, in any order of rows."""
    neg_inf = np.float32(-np.inf)
    with_shadow = grey.shape[0] > 0
    hmax = ii.shape[1] - 1
    nmax = 1
    for k in range(plan.shape[0]):
        nmax = max(nmax, plan[k, 4])
    num, s_in, s_below = np.empty(nmax), np.empty(nmax), np.empty(nmax)  # float64 sums
    val, fac = np.empty(nmax, np.float32), np.empty(nmax, np.float32)  # S then V; the vegetation factor
    for b in range(ii.shape[0]):
        ob = out[b]
        us = shadow[b] if shadow.shape[0] > 0 else np.empty(0)  # U, where it is not applied here
        for t in range(order.shape[0]):
            k, j = order[t, 0], order[t, 1]
            w, h, sx, sy, nx, ny, oy, off, dx, dy, cw, ch, lo, sh, mx, gdx, gdy, gw, gh = plan[k]
            y0 = oy + j * sy
            y1 = y0 + h
            wl = alpha * loc[lo + j] + beta_r
            row = off + j * nx
            _row_edge_scores(ii[b, y0 + dy], ii[b, y0 + dy + ch], anchor[b, y0], anchor[b, y1], cut_col[b, y0],
                             cut_col[b, y1], cut_row[b, y1], corner[b, y1], nx, sx, w, dx, cw, unit, denom[k],
                             num, val)
            if green.shape[0] > 0:
                _row_vegetation(green[b, y0 + gdy], green[b, y0 + gdy + gh], nx, sx, gdx, gw, 1.0 / float(gw * gh),
                                veg_power, fac)
                for i in range(nx):
                    s = val[i]
                    val[i] = (s * wl) * fac[i] if s >= min_edge else neg_inf
            else:
                for i in range(nx):
                    s = val[i]
                    val[i] = s * wl if s >= min_edge else neg_inf
            if not with_shadow:
                o = ob[row: row + nx]
                for i in range(nx):
                    o[i] = val[i]
                continue
            yb = min(y1 + sh, hmax)
            _row_shadow(grey[b, y1 - sh], grey[b, y1], grey[b, yb], nx, sx, w, mx, yb > y1,
                        float(sh * (w - 2 * mx)), float(max(yb - y1, 1) * (w - 2 * mx)), sqrt_floor,
                        s_in, s_below, val, ob, us, row)


def row_order(plan: np.ndarray) -> np.ndarray:
    """The window rows of ``plan`` (:data:`PLAN_COLUMNS`), ``int64 [Σ ny, 2]`` (size, row),
    by their bottom row, then size: rows that read the same table rows (four of the five
    tables at the bottom, the grey strips) come together while those rows are in cache
    (timed against size by size with ``benchmarks/kernel_ab.py``)."""
    ny = plan[:, 5]
    k = np.repeat(np.arange(plan.shape[0], dtype=np.int64), ny)
    j = np.arange(int(ny.sum()), dtype=np.int64) - np.repeat(np.cumsum(ny) - ny, ny)
    bottom = plan[k, 6] + j * plan[k, 3] + plan[k, 1]  # oy + j·sy + h
    keep = np.lexsort((k, bottom))
    return np.ascontiguousarray(np.stack([k[keep], j[keep]], 1))


def score_grid_cpu(ii: Tensor, tables, plan: np.ndarray, denom: np.ndarray, loc: np.ndarray, unit: float,
                   alpha: float, beta_r: float, min_edge: float, out: Tensor, grey: Tensor | None = None,
                   shadow: Tensor | None = None, sqrt_floor: float | None = None,
                   green: Tensor | None = None, veg_power: int = 1, order: np.ndarray | None = None) -> None:
    """Fill ``out`` (``float32 [B, N]``, CPU) with V of every window, compiled (numba);
    given ``grey`` (``float64 (B, H + 1, W + 1)`` integral image of the grey image), also
    ``shadow`` (``float64 [B, N]``) with U of :func:`shadow_fraction` (the factor is applied
    by :func:`apply_shadow`, in torch, for both paths), or with ``sqrt_floor`` (the shadow
    floor, for a shadow power of 0.5) V times sqrt(floor + U) directly (``shadow`` unused).

    Args:
        ii: ``float64 (B, H + 1, W + 1)`` integral image of the edge map.
        tables: :class:`reeb_torch.stages.enclosed.EnclosedTables` of the groups (every window
            wider and taller than their ``max_extent``).
        plan: ``int64 [S, 19]``, one row per window size (:data:`PLAN_COLUMNS`).
        denom: ``float64 [S]``, eq. 1's normaliser of each size (input-pixel units).
        loc: ``float32 [Σ ny]``, L of each size's rows, at ``plan[:, 12]``.
        unit, alpha: as in :func:`edge_score` and :func:`combined_score`.
        beta_r: β·R for a constant road term R (0 for ``road_score='none'``).
        min_edge: windows with S below this get ``-inf``.
        green, veg_power: ``int32 (B, H + 1, W + 1)`` pixel counts of the green mask
            (:func:`count_integral`) and the power of :func:`vegetation_factor` (``None``:
            no vegetation term).
        order: :func:`row_order` of ``plan``, where the caller keeps it (else computed here).
    """
    f32 = np.float32
    g = np.zeros((0, 1, 1)) if grey is None else grey.numpy()
    gr = np.zeros((0, 1, 1), np.int32) if green is None else green.numpy()
    u = np.zeros((0, 1)) if shadow is None else shadow.numpy()
    per_image = [ii.numpy(), tables.anchor.numpy(), tables.cut_col.numpy(), tables.cut_row.numpy(),
                 tables.corner.numpy()]
    order = row_order(plan) if order is None else order
    consts = (denom, loc, float(unit), f32(alpha), f32(beta_r), f32(min_edge))
    sq = -1.0 if sqrt_floor is None else float(sqrt_floor)

    if ii.shape[0] % 2 == 0:  # the two cores take half the images each (each its own tables)

        def run(lo: int, hi: int) -> None:
            _score_grid_kernel(*(a[lo:hi] for a in per_image), plan, order, *consts, out.numpy()[lo:hi],
                               g[lo:hi] if g.shape[0] else g, u[lo:hi] if u.shape[0] else u, sq,
                               gr[lo:hi] if gr.shape[0] else gr, int(veg_power))

        on_two_cores(run, ii.shape[0])
        return
    # an odd batch (one image: the latency a detector sees): every other window row each, for
    # every image (each row writes its own part of ``out``)
    parts = [np.ascontiguousarray(order[i::2]) for i in (0, 1)]

    def run_rows(lo: int, hi: int) -> None:
        for part in parts[lo:hi]:
            _score_grid_kernel(*per_image, plan, part, *consts, out.numpy(), g, u, sq, gr, int(veg_power))

    on_two_cores(run_rows, len(parts))


def shadow_strips(w: int, h: int, strip: float, margin: float) -> tuple[int, int]:
    """Rows ``sh`` of the two shadow strips and columns ``mx`` left out on each side, for a
    ``w × h`` box (``ReebConfig.shadow_strip`` / ``shadow_margin``): ``sh >= 1`` and at
    least one column stays."""
    return max(1, int(round(strip * h))), min(int(margin * w), (w - 1) // 2)


def shadow_fraction(inside_sum: Tensor, below_sum: Tensor, inside_n: Tensor | float,
                    below_n: Tensor) -> Tensor:
    """U of ``ReebConfig.shadow_score='underneath'``: how much darker a box's bottom strip
    is than the strip just below it, ``clamp((g_below − g_inside) / g_below, 0, 1)``, from
    the grey sums and pixel counts of the two strips (``float64``); 0 where no pixel lies
    below (``below_n == 0``). Same shape as the sums, in [0, 1]."""
    g_in = inside_sum / inside_n
    g_below = below_sum / below_n.clamp(min=1)
    u = ((g_below - g_in) / g_below.clamp(min=1e-3)).clamp(0.0, 1.0)
    return torch.where(below_n > 0, u, torch.zeros_like(u))


def vegetation_factor(green_sum: Tensor, area: Tensor | float, power: int) -> Tensor:
    """(1 − G)^power with G = ``green_sum · (1 / area)``, the green-dominant fraction of a
    box (``ReebConfig.vegetation_score='green'``), ``float64``, as a product of ``power``
    factors (the compiled pass computes the same numbers)."""
    q = 1.0 - green_sum.to(torch.float64) * (1.0 / area)
    f = q
    for _ in range(power - 1):
        f = f * q
    return f


def apply_shadow(v: Tensor, u: Tensor, floor: float, power: float) -> Tensor:
    """V·(floor + U)^power where V is finite (``-inf`` stays), ``float32``; ``u`` is ``float64``
    of V's shape. A power of 0.5 is a correctly rounded square root on every path (numpy's
    on the CPU, where torch's vectorised one may differ by an ulp; CUDA's is IEEE), as the
    compiled pass computes it, so both give the same numbers."""
    if power == 0.5 and u.device.type == "cpu":
        f = torch.from_numpy(np.sqrt(u.numpy() + floor)).float()
    else:
        f = (u + floor).pow(power).float()
    return torch.where(torch.isfinite(v), v * f, v)


@numba.njit(cache=True, nogil=True)
def _select_kernel(scores: np.ndarray, members: np.ndarray, starts: np.ndarray, budget: np.ndarray,
                   chosen: np.ndarray) -> None:  # pragma: no cover - compiled
    """For each image and region, mark the ``budget`` best finite scores among the region's
    windows (``members[starts[r]:starts[r + 1]]``, ascending); ties at the cut go to the
    lower window index."""
    for i in range(scores.shape[0]):
        for r in range(starts.shape[0] - 1):
            idx = members[starts[r]: starts[r + 1]]
            n = idx.shape[0]
            k = min(budget[i, r], n)
            if k <= 0:
                continue
            vals = np.empty(n, np.float32)
            row = scores[i]
            for j in range(n):
                vals[j] = row[idx[j]]
            finite = 0
            for j in range(n):  # the counts without branches: loops the compiler vectorises (the marks keep
                # theirs: one image's regions overlap across the two cores, which only ever write True)
                finite += np.isfinite(vals[j])
            out = chosen[i]
            if finite <= k:
                for j in range(n):
                    if np.isfinite(vals[j]):
                        out[idx[j]] = True
                continue
            t = kth_largest(vals, k)  # finite: more than k are
            above = 0
            for j in range(n):
                above += vals[j] > t
            for j in range(n):
                if vals[j] > t:
                    out[idx[j]] = True
            left = k - above
            for j in range(n):
                if left == 0:
                    break
                if vals[j] == t:
                    out[idx[j]] = True
                    left -= 1


def select_per_region_cpu(scores: Tensor, members: np.ndarray, starts: np.ndarray, budget: Tensor) -> Tensor:
    """Eq. 9's per-region selection on the CPU, compiled: ``bool [B, N]`` marking, for each
    image ``b`` and region ``r``, the ``budget[b, r]`` best finite scores among the region's
    windows ``members[starts[r]:starts[r + 1]]`` (ascending window indices; the lower index
    wins a tie at the cut). ``scores``: ``float32 [B, N]``; ``budget``: ``int64 [B, R]``."""
    chosen = _scratch.empty("select.chosen", tuple(scores.shape), np.bool_)
    chosen.fill(False)
    sc, bu = scores.contiguous().numpy(), budget.contiguous().numpy()
    # one image: half the regions each (a window in two overlapping regions may be marked
    # by both threads, each writing True)
    images_or_rows(lambda lo, hi, r0, r1: _select_kernel(sc[lo:hi], members, starts[r0: r1 + 1], bu[lo:hi, r0:r1],
                                                         chosen[lo:hi]), sc.shape[0], len(starts) - 1)
    return torch.from_numpy(chosen)
