"""Eq. 1's enclosed sums at any box and for every window of a size, from prefix tables.

Scoring a box needs eq. 1's enclosed sum (the mass of the edge groups wholly inside it)
at arbitrary coordinates. :class:`EnclosedTables` gives it exactly in O(1) per box from four
prefix-sum tables, when no edge group is wider or taller than the box minus one
(``group_cell`` set bounds groups to one tile):

    Σ_enclosed = A(box) − C_col(X1; Y0..Y1) − C_row(Y1; X0..X1) + K(X1, Y1)

with A the mass of groups whose top-left corner ``(x1, y1)`` lies in the box,
C_col the mass of groups anchored in rows ``[Y0, Y1)`` that straddle column ``X1``
(``x1 < X1 <= x2``), C_row likewise for row ``Y1``, and K the mass of groups that
straddle both (inclusion–exclusion; groups anchored inside can only leave the box
through its right or bottom side).
"""

from __future__ import annotations

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
           "enclosed_grid"]


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
