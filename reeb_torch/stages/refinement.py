"""Edge Boxes' box refinement (Zitnick & Dollár, ECCV 2014, Sec. 3.2), vectorised.

The sliding-window grid puts a box at most half a stride from the best box of its size;
Edge Boxes closes that gap by moving each side of the best candidates while the exact
score improves: each round tries ±step on each of the four sides in turn and keeps an
improvement; the step starts at half the window stride and halves down to one working
pixel. Here every candidate of a batch moves at once (one tensor op per side and sign).

Scoring a box that is not on the grid needs eq. 1's enclosed sum at arbitrary
coordinates. :class:`EnclosedTables` gives it exactly in O(1) per box from four
prefix-sum tables, when no edge group is wider or taller than the box minus one
(``grouping='connected'`` with ``group_cell`` set bounds groups to one tile):

    Σ_enclosed = A(box) − C_col(X1; Y0..Y1) − C_row(Y1; X0..X1) + K(X1, Y1)

with A the mass of groups whose top-left corner ``(x1, y1)`` lies in the box,
C_col the mass of groups anchored in rows ``[Y0, Y1)`` that straddle column ``X1``
(``x1 < X1 <= x2``), C_row likewise for row ``Y1``, and K the mass of groups that
straddle both (inclusion–exclusion; groups anchored inside can only leave the box
through its right or bottom side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np
import torch
from torch import Tensor

from . import _scratch
from ._threads import on_two_cores, started
from .groups import EdgeGroups

__all__ = ["EnclosedTables", "enclosed_tables", "enclosed_tables_started", "box_sum_at", "enclosed_at",
           "enclosed_grid", "refine_boxes"]


@dataclass
class EnclosedTables:
    """Prefix-sum tables of the edge groups of a ``(B, H, W)`` working image, ``float64``.

    Attributes:
        anchor: ``[B, H + 1, W + 1]`` integral image of group mass at ``(y1, x1)``.
        cut_col: ``[B, H + 1, W + 2]``; ``cut_col[b, y, X]`` = mass of the groups anchored
            in rows ``< y`` that straddle column ``X`` (``x1 < X <= x2``).
        cut_row: ``[B, H + 2, W + 1]``; ``cut_row[b, Y, x]`` = mass of the groups anchored
            in columns ``< x`` that straddle row ``Y`` (``y1 < Y <= y2``).
        corner: ``[B, H + 2, W + 2]``; mass of the groups straddling both column ``X`` and row ``Y``.
        max_extent: the largest ``x2 − x1`` or ``y2 − y1`` of any group (the sums are exact
            for boxes wider and taller than this).
    """

    anchor: Tensor
    cut_col: Tensor
    cut_row: Tensor
    corner: Tensor
    max_extent: int


@numba.njit(cache=True, nogil=True)
def _tables_kernel(b: np.ndarray, x1: np.ndarray, y1: np.ndarray, x2: np.ndarray, y2: np.ndarray, m: np.ndarray,
                   first: int, anchor: np.ndarray, cut_col: np.ndarray, cut_row: np.ndarray,
                   corner: np.ndarray) -> None:  # pragma: no cover - compiled
    """The four tables of :func:`_enclosed_tables_torch` for images ``first, first + 1, …``:
    zeroed in order, the same difference entries, then their 2-D prefix sums, the four
    tables a row at a time together (every entry is an exact float64 sum, so the order of
    the additions does not matter; it is the previous order all the same)."""
    for t in (anchor, cut_col, cut_row, corner):
        t.fill(0.0)
    for g in range(b.shape[0]):
        i, mg = b[g] - first, m[g]
        anchor[i, y1[g] + 1, x1[g] + 1] += mg
        cut_col[i, y1[g] + 1, x1[g] + 1] += mg
        cut_col[i, y1[g] + 1, x2[g] + 1] -= mg
        cut_row[i, y1[g] + 1, x1[g] + 1] += mg
        cut_row[i, y2[g] + 1, x1[g] + 1] -= mg
        corner[i, y1[g] + 1, x1[g] + 1] += mg
        corner[i, y1[g] + 1, x2[g] + 1] -= mg
        corner[i, y2[g] + 1, x1[g] + 1] -= mg
        corner[i, y2[g] + 1, x2[g] + 1] += mg
    # the 2-D prefix sums, the four tables' rows side by side (four independent running
    # sums, each entry the row's running sum plus the entry above, as before)
    hp, wp = corner.shape[1], corner.shape[2]  # H + 2, W + 2
    h1, w1 = hp - 1, wp - 1  # anchor's shape
    zero = np.zeros(wp)  # the row above row 0 (adding +0.0 to a running sum changes no bit)
    spare = np.zeros((2, wp))  # anchor's and cut_col's stand-ins on the last row (only theirs)
    for i in range(anchor.shape[0]):
        at, ct, rt, kt = anchor[i], cut_col[i], cut_row[i], corner[i]
        for y in range(hp):
            a = 0.0
            c = 0.0
            r = 0.0
            k = 0.0
            if y == h1:
                spare.fill(0.0)
            ar, cr = (at[y], ct[y]) if y < h1 else (spare[0], spare[1])
            ap, cp = (at[y - 1], ct[y - 1]) if 0 < y < h1 else (zero, zero)
            rr, kr = rt[y], kt[y]
            rp, kp = (rt[y - 1], kt[y - 1]) if y > 0 else (zero, zero)
            for x in range(w1):
                a += ar[x]
                ar[x] = a + ap[x]
                c += cr[x]
                cr[x] = c + cp[x]
                r += rr[x]
                rr[x] = r + rp[x]
                k += kr[x]
                kr[x] = k + kp[x]
            c += cr[w1]
            cr[w1] = c + cp[w1]
            k += kr[w1]
            kr[w1] = k + kp[w1]


def enclosed_tables(groups: EdgeGroups, batch: int, height: int, width: int) -> EnclosedTables:
    """Build :class:`EnclosedTables` for ``groups`` of a ``batch × height × width`` image.

    On the CPU a compiled pass (numba) fills the tables, the two halves of the batch on two
    cores; elsewhere tensor scatters and cumulative sums. The numbers are the same: every
    entry is a float64 sum of the groups' float64 masses, which is exact (tested equal)."""
    if groups.batch.device.type != "cpu":
        return _enclosed_tables_torch(groups, batch, height, width)
    run, tables = _tables_job(groups, batch, height, width)
    on_two_cores(run, batch)
    return tables


def enclosed_tables_started(groups: EdgeGroups, batch: int, height: int,
                            width: int) -> Callable[[], EnclosedTables]:
    """:func:`enclosed_tables` on the CPU, the compiled pass started on the helper thread
    (:func:`reeb_torch.stages._threads.started`) for the whole batch: returns the function
    that waits for it and gives the tables (the same numbers)."""
    run, tables = _tables_job(groups, batch, height, width)
    wait = started(lambda: run(0, batch))

    def done() -> EnclosedTables:
        wait()
        return tables

    return done


def _tables_job(groups: EdgeGroups, batch: int, height: int,
                width: int) -> tuple[Callable[[int, int], None], EnclosedTables]:
    """The compiled pass of :func:`enclosed_tables` as ``run(lo, hi)`` (images ``[lo,
    hi)``), and the tables it fills."""
    h, w = height, width
    # np.empty, zeroed in order by the kernel: a calloc'd buffer would fault its pages in
    # during the scattered writes instead, which costs more than the whole pass
    tabs = [_scratch.empty("tables.anchor", (batch, h + 1, w + 1)), _scratch.empty("tables.cut_col", (batch, h + 1, w + 2)),
            _scratch.empty("tables.cut_row", (batch, h + 2, w + 1)), _scratch.empty("tables.corner", (batch, h + 2, w + 2))]
    fields = [groups.batch, groups.x1, groups.y1, groups.x2, groups.y2, groups.magnitude.to(torch.float64)]
    *cols, mass = [f.contiguous().numpy() for f in fields]
    if batch > 1 and len(groups) > 1 and not (cols[0][1:] >= cols[0][:-1]).all():
        order = np.argsort(cols[0], kind="stable")  # image by image (the sums are exact in any order)
        *cols, mass = [np.ascontiguousarray(f[order]) for f in (*cols, mass)]
    starts = np.searchsorted(cols[0], np.arange(batch + 1))

    def run(lo: int, hi: int) -> None:
        a, z = starts[lo], starts[hi]
        _tables_kernel(*(c[a:z] for c in cols), mass[a:z], lo, *(t[lo:hi] for t in tabs))

    anchor, cut_col, cut_row, corner = (torch.from_numpy(t) for t in tabs)
    return run, EnclosedTables(anchor, cut_col, cut_row, corner, groups.max_extent)


def _enclosed_tables_torch(groups: EdgeGroups, batch: int, height: int, width: int) -> EnclosedTables:
    """:func:`enclosed_tables` as tensor scatters and cumulative sums (any device)."""
    dev = groups.batch.device
    f64 = torch.float64
    b, x1, y1, x2, y2 = groups.batch, groups.x1, groups.y1, groups.x2, groups.y2
    m = groups.magnitude.to(f64)
    h, w = height, width

    def scatter(shape: tuple[int, int], ys: list[Tensor], xs: list[Tensor], signs: list[float]) -> Tensor:
        buf = torch.zeros(batch * shape[0] * shape[1], dtype=f64, device=dev)
        idx = torch.cat([(b * shape[0] + yy) * shape[1] + xx for yy, xx in zip(ys, xs)])
        val = torch.cat([m * s for s in signs])
        buf.index_put_((idx,), val, accumulate=True)
        return buf.view(batch, *shape)

    anchor = torch.zeros(batch, h + 1, w + 1, dtype=f64, device=dev)
    anchor[:, 1:, 1:] = scatter((h, w), [y1], [x1], [1.0]).cumsum(2).cumsum(1)
    # straddling column X: +m at X = x1 + 1, −m at X = x2 + 1 (row y1), cumsum over X, then rows
    d = scatter((h, w + 2), [y1, y1], [x1 + 1, x2 + 1], [1.0, -1.0]).cumsum(2)
    cut_col = torch.zeros(batch, h + 1, w + 2, dtype=f64, device=dev)
    cut_col[:, 1:] = d.cumsum(1)
    d = scatter((h + 2, w), [y1 + 1, y2 + 1], [x1, x1], [1.0, -1.0]).cumsum(1)
    cut_row = torch.zeros(batch, h + 2, w + 1, dtype=f64, device=dev)
    cut_row[:, :, 1:] = d.cumsum(2)
    corner = scatter((h + 2, w + 2), [y1 + 1, y1 + 1, y2 + 1, y2 + 1], [x1 + 1, x2 + 1, x1 + 1, x2 + 1],
                     [1.0, -1.0, -1.0, 1.0]).cumsum(2).cumsum(1)
    return EnclosedTables(anchor, cut_col, cut_row, corner, groups.max_extent)


def _at(t: Tensor, b: Tensor, y: Tensor, x: Tensor) -> Tensor:
    return t[b, y, x]


def box_sum_at(ii: Tensor, b: Tensor, x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor) -> Tensor:
    """Sums over the pixel boxes ``[x0, x1) × [y0, y1)`` (int64 ``[K]`` each, within the
    image) of images ``b`` from an integral image ``(B, H + 1, W + 1)``."""
    return _at(ii, b, y1, x1) - _at(ii, b, y0, x1) - _at(ii, b, y1, x0) + _at(ii, b, y0, x0)


def enclosed_at(t: EnclosedTables, b: Tensor, x0: Tensor, y0: Tensor, x1: Tensor, y1: Tensor) -> Tensor:
    """Σ of eq. 1 (mass of the groups wholly inside ``[x0, x1) × [y0, y1)``) for boxes at
    least ``max_extent + 1`` wide and tall, ``float64 [K]``."""
    a = box_sum_at(t.anchor, b, x0, y0, x1, y1)
    col = _at(t.cut_col, b, y1, x1) - _at(t.cut_col, b, y0, x1)
    row = _at(t.cut_row, b, y1, x1) - _at(t.cut_row, b, y1, x0)
    return a - col - row + _at(t.corner, b, y1, x1)


def enclosed_grid(t: EnclosedTables, s) -> Tensor:
    """Σ of eq. 1 for every position of the window size ``s`` (a
    :class:`reeb_torch.stages.windows.WindowSize`), ``float64 (B, ny, nx)``, from strided slices of
    the tables (no scatter per size). Exact, and equal to
    :func:`reeb_torch.stages.scoring.enclosed_sums`, when ``s.w`` and ``s.h`` exceed ``max_extent``."""
    def at(table: Tensor, dy: int, dx: int) -> Tensor:
        oy, ox = s.oy + dy, dx
        return table[:, oy: oy + (s.ny - 1) * s.sy + 1: s.sy, ox: ox + (s.nx - 1) * s.sx + 1: s.sx]

    a = at(t.anchor, s.h, s.w) - at(t.anchor, 0, s.w) - at(t.anchor, s.h, 0) + at(t.anchor, 0, 0)
    col = at(t.cut_col, s.h, s.w) - at(t.cut_col, 0, s.w)
    row = at(t.cut_row, s.h, s.w) - at(t.cut_row, s.h, 0)
    return a - col - row + at(t.corner, s.h, s.w)


def _first_steps(boxes: Tensor, step_fraction: float) -> Tensor:
    """The first step of each box's sides, ``int64 [K, 2]`` (x, y): half the window stride,
    ``step_fraction · side / 2``, rounded, at least one pixel."""
    wh = (boxes[:, 2:] - boxes[:, :2]).to(torch.float64)
    return torch.clamp((wh * (step_fraction / 2)).round().long(), min=1)


def refine_boxes(boxes: Tensor, b: Tensor, score_fn, width: int, height: int, min_side: int,
                 step_fraction: float) -> tuple[Tensor, Tensor]:
    """Move each side of ``boxes`` (int64 ``[K, 4]``, working pixels, ``x1, y1`` exclusive)
    while ``score_fn(boxes, b) -> [K]`` improves (Edge Boxes' refinement).

    The step of the left/right sides starts at ``step_fraction · width / 2`` (half the
    window stride), that of the top/bottom at ``step_fraction · height / 2``, and halves
    to one pixel. Boxes stay inside the image and at least ``min_side`` wide and tall.
    Returns the refined boxes and their scores.
    """
    boxes = boxes.clone()
    best = score_fn(boxes, b)
    step = _first_steps(boxes, step_fraction)
    limit = torch.tensor([width, height, width, height], device=boxes.device)
    for _ in range(int(math.ceil(math.log2(max(2, int(step.max()))))) + 1):
        for side in range(4):
            s = step[:, side % 2]
            for sign in (1, -1):
                cand = boxes.clone()
                cand[:, side] += sign * s
                c = cand
                ok = ((c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 2] <= limit[2]) & (c[:, 3] <= limit[3])
                      & (c[:, 2] - c[:, 0] >= min_side) & (c[:, 3] - c[:, 1] >= min_side) & (s > 0))
                if not bool(ok.any()):
                    continue
                idx = torch.nonzero(ok).squeeze(1)
                sc = score_fn(cand[idx], b[idx])
                better = sc > best[idx]
                win = idx[better]
                boxes[win] = cand[win]
                best[win] = sc[better]
        step = torch.div(step, 2, rounding_mode="floor")
        if int(step.max()) == 0:
            break
    return boxes, best


# ---------------------------------------------------------------------------------------
# compiled CPU path: the whole refinement of every box in one pass
# ---------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True, inline="always")
def _sum(t: np.ndarray, i: int, x0: int, y0: int, x1: int, y1: int) -> float:  # pragma: no cover - compiled
    """:func:`box_sum_at` of one box (the same operations in the same order)."""
    return ((t[i, y1, x1] - t[i, y0, x1]) - t[i, y1, x0]) + t[i, y0, x0]


@numba.njit(cache=True, nogil=True, inline="always")
def _centred(x0: int, y0: int, w: int, h: int, fraction: np.float32) -> tuple[int, int, int, int]:  # pragma: no cover
    """The centred ``fraction`` of a box as the tensor scorer places it (float32 products,
    rounded half to even, at least one pixel)."""
    cw = max(1, int(np.rint(np.float32(w) * fraction)))
    ch = max(1, int(np.rint(np.float32(h) * fraction)))
    cx0 = x0 + (w - cw) // 2
    cy0 = y0 + (h - ch) // 2
    return cx0, cy0, cx0 + cw, cy0 + ch


@numba.njit(cache=True, nogil=True)
def _box_score(i: int, x0: int, y0: int, x1: int, y1: int, anchor: np.ndarray, cut_col: np.ndarray,
               cut_row: np.ndarray, corner: np.ndarray, ii: np.ndarray, loc_h: np.ndarray, loc_w: np.ndarray,
               norm: np.ndarray, green: np.ndarray, grey: np.ndarray, params: np.ndarray, iparams: np.ndarray,
               ) -> float:  # pragma: no cover - compiled
    """V of one box, with the operations of the tensor box scorer in the same order (so the
    same float64 numbers): see :func:`refine_boxes_cpu` for ``params`` / ``iparams``."""
    unit, alpha_loc_road, centre_f, veg_f, strip, margin, floor = (
        params[0], params[1], np.float32(params[2]), np.float32(params[3]), params[4], params[5], params[6])
    beta_road, veg_power, with_green, with_shadow, hk = params[7], iparams[0], iparams[1], iparams[2], iparams[3]
    w = x1 - x0
    h = y1 - y0
    cx0, cy0, cx1, cy1 = _centred(x0, y0, w, h, centre_f)
    centre = _sum(ii, i, cx0, cy0, cx1, cy1)
    a = _sum(anchor, i, x0, y0, x1, y1)
    col = cut_col[i, y1, x1] - cut_col[i, y0, x1]
    row = cut_row[i, y1, x1] - cut_row[i, y1, x0]
    enc = ((a - col) - row) + corner[i, y1, x1]
    s = (enc * unit - centre * unit) / norm[w, h]
    loc = loc_h[0, y1, h] * loc_w[0, y1, w]
    for c in range(1, loc_h.shape[0]):  # the best class, as the tensor location score's maximum
        loc = max(loc, loc_h[c, y1, h] * loc_w[c, y1, w])
    v = s * (alpha_loc_road * loc + beta_road)
    if with_green:
        gx0, gy0, gx1, gy1 = _centred(x0, y0, w, h, veg_f)
        gs = _sum(green, i, gx0, gy0, gx1, gy1)
        q = 1.0 - float(gs) * (1.0 / float((gx1 - gx0) * (gy1 - gy0)))
        f = q
        for _ in range(veg_power - 1):
            f = f * q
        v = v * f
    if with_shadow:
        sh = max(1, int(np.rint(float(h) * strip)))
        mx = min(int(np.floor(float(w) * margin)), (w - 1) // 2)
        ax0, ax1 = x0 + mx, x1 - mx
        inside = _sum(grey, i, ax0, y1 - sh, ax1, y1)
        below = _sum(grey, i, ax0, y1, ax1, y1 + sh)
        rows = min(max(hk - y1, 0), sh)
        n_below = rows * (ax1 - ax0)
        u = 0.0
        if n_below > 0:
            g_in = inside / float(sh * (ax1 - ax0))
            g_below = below / float(max(n_below, 1))
            u = min(max((g_below - g_in) / max(g_below, 1e-3), 0.0), 1.0)
        if np.isfinite(v):
            v = v * float(np.float32(np.sqrt(u + floor)))
    return v


@numba.njit(cache=True, nogil=True)
def _refine_kernel(boxes: np.ndarray, bi: np.ndarray, steps: np.ndarray, best: np.ndarray, anchor: np.ndarray,
                   cut_col: np.ndarray, cut_row: np.ndarray, corner: np.ndarray, ii: np.ndarray, loc_h: np.ndarray,
                   loc_w: np.ndarray, norm: np.ndarray, green: np.ndarray, grey: np.ndarray, params: np.ndarray, iparams: np.ndarray,
                   width: int, height: int, min_side: int) -> None:  # pragma: no cover - compiled
    """:func:`refine_boxes` box by box (each box's moves depend only on its own scores)."""
    for k in range(boxes.shape[0]):
        i = bi[k]
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        cur = _box_score(i, x0, y0, x1, y1, anchor, cut_col, cut_row, corner, ii, loc_h, loc_w, norm, green,
                         grey, params, iparams)
        sx, sy = steps[k, 0], steps[k, 1]
        while sx > 0 or sy > 0:
            for side in range(4):
                st = sx if side % 2 == 0 else sy
                if st <= 0:
                    continue
                for sign in (1, -1):
                    c0, c1, c2, c3 = x0, y0, x1, y1
                    if side == 0:
                        c0 += sign * st
                    elif side == 1:
                        c1 += sign * st
                    elif side == 2:
                        c2 += sign * st
                    else:
                        c3 += sign * st
                    if c0 < 0 or c1 < 0 or c2 > width or c3 > height or c2 - c0 < min_side or c3 - c1 < min_side:
                        continue
                    sc = _box_score(i, c0, c1, c2, c3, anchor, cut_col, cut_row, corner, ii, loc_h, loc_w, norm,
                                    green, grey, params, iparams)
                    if sc > cur:
                        x0, y0, x1, y1, cur = c0, c1, c2, c3, sc
            sx //= 2
            sy //= 2
        boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = x0, y0, x1, y1
        best[k] = cur


def refine_boxes_cpu(boxes: Tensor, b: Tensor, tables: EnclosedTables, ii_edges: Tensor, loc_h: Tensor,
                     loc_w: Tensor, norm: Tensor, green: Tensor | None, grey_below: Tensor | None, params: dict,
                     width: int, height: int, min_side: int, step_fraction: float) -> tuple[Tensor, Tensor]:
    """:func:`refine_boxes` with the box scorer of the package default compiled (numba), one
    box after the other: the same moves and the same float64 scores as the tensor scorer
    (tested equal), without a tensor op per side, sign and step.

    ``max_c loc_h[c, y1, h] · loc_w[c, y1, w]`` and ``norm[w, h]`` are the location score
    and eq. 1's normaliser of a box of height ``h`` and width ``w`` whose bottom is working
    row ``y1``, tabulated by the tensor functions themselves (``float64``; one ``c`` and
    ``loc_w = 1`` where L does not read the width); ``green`` the green-pixel counts (``int32``, read as they are; or
    None), ``grey_below`` the grey integral image extended below the image (or None: no
    shadow term); ``params`` holds
    ``unit, alpha, beta_road, center_fraction, vegetation_box, vegetation_power,
    shadow_strip, shadow_margin, shadow_floor``."""
    boxes = boxes.clone().contiguous()
    steps = _first_steps(boxes, step_fraction).contiguous()
    best = torch.empty(len(boxes), dtype=torch.float64)
    p = np.array([params["unit"], params["alpha"], params["center_fraction"], params["vegetation_box"],
                  params["shadow_strip"], params["shadow_margin"], params["shadow_floor"], params["beta_road"]],
                 np.float64)
    ip = np.array([params["vegetation_power"], green is not None, grey_below is not None, height], np.int64)
    arrays = (tables.anchor.numpy(), tables.cut_col.numpy(), tables.cut_row.numpy(), tables.corner.numpy(),
              ii_edges.contiguous().numpy(), loc_h.contiguous().numpy(), loc_w.contiguous().numpy(),
              norm.contiguous().numpy(),
              green.contiguous().numpy() if green is not None else np.zeros((1, 1, 1), np.int32),
              grey_below.contiguous().numpy() if grey_below is not None else np.zeros((1, 1, 1)))
    bx, bb, st, out = boxes.numpy(), b.contiguous().numpy(), steps.numpy(), best.numpy()

    def run(lo: int, hi: int) -> None:  # boxes are independent: each core takes a share
        _refine_kernel(bx[lo:hi], bb[lo:hi], st[lo:hi], out[lo:hi], *arrays, p, ip, width, height, min_side)

    on_two_cores(run, len(bx))
    return boxes, best
