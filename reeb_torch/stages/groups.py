"""Sec. 3.7 — edge groups: adjacent edge pixels form one group, with its magnitude sum
(``m_n`` of eq. 1) and bounding box.

The groups are the 8-connected components of edge pixels: on the CPU a compiled
union–find in one raster pass, elsewhere min-label propagation with pointer jumping over
the edge pixels only (batched tensor ops; the same groups). With ``cell`` set
(``ReebConfig.group_cell``), the components are cut at the borders of ``cell × cell``
tiles, which bounds the size of a group (reading 2); with ``cell=None`` they are plain
connected components, as printed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from ._threads import on_two_cores

__all__ = ["EdgeGroups", "connected_groups", "label_components"]


@dataclass
class EdgeGroups:
    """Edge groups of a batch, flattened over images.

    Attributes (``G`` groups in total):
        batch: ``int64 [G]`` image index of each group.
        x1, y1, x2, y2: ``int64 [G]`` inclusive pixel bounds of the group's pixels.
        magnitude: ``float64 [G]`` sum of the edge magnitudes of the group's pixels (exact).
    """

    batch: Tensor
    x1: Tensor
    y1: Tensor
    x2: Tensor
    y2: Tensor
    magnitude: Tensor

    def __len__(self) -> int:
        return int(self.batch.numel())

    @functools.cached_property
    def max_extent(self) -> int:
        """The largest ``x2 − x1`` or ``y2 − y1`` of any group (0 without groups): window
        sums from prefix tables are exact for windows wider and taller than this (worked
        out once; the fields are not to be changed after)."""
        if not len(self):
            return 0
        if self.x1.device.type == "cpu":  # numpy's small ops cost a fraction of torch's
            x1, y1, x2, y2 = (t.numpy() for t in (self.x1, self.y1, self.x2, self.y2))
            return int(np.maximum(x2 - x1, y2 - y1).max())
        return int(torch.maximum(self.x2 - self.x1, self.y2 - self.y1).max())


def _coords(b: int, h: int, w: int, device: torch.device) -> tuple[Tensor, Tensor]:
    ys = torch.arange(h, device=device).view(1, h, 1).expand(b, h, w)
    xs = torch.arange(w, device=device).view(1, 1, w).expand(b, h, w)
    return xs, ys


_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def label_components(mask: Tensor, cell: int | None = None, max_iter: int = 100_000) -> Tensor:
    """8-connected component labels of a bool mask ``(N, h, w)``.

    Works on the foreground pixels only, with the hooking and shortcutting steps of the
    FastSV algorithm (Zhang, Azad, Hu, "FastSV", SIAM PP 2020): each pixel's smallest
    neighbour label is hooked onto the root its label names, then labels jump to their
    label's label, until nothing changes (a few iterations, logarithmic in the chain length). Components do not cross the ``N`` planes, nor the
    borders of ``cell × cell`` tiles when ``cell`` is set.

    Returns ``int64 (N, h, w)``: for each foreground pixel the smallest flat index (into
    ``mask.view(-1)``) of its component, ``-1`` for background.
    """
    n, h, w = mask.shape
    dev = mask.device
    pix = torch.nonzero(mask.reshape(-1)).squeeze(1)  # ascending flat indices
    e = pix.numel()
    out = torch.full((n * h * w,), -1, dtype=torch.long, device=dev)
    if e == 0:
        return out.view(n, h, w)
    ids = torch.arange(e, device=dev)
    idmap = out.clone()
    idmap[pix] = ids
    plane, rem = torch.div(pix, h * w, rounding_mode="floor"), pix % (h * w)
    y, x = torch.div(rem, w, rounding_mode="floor"), rem % w
    nbrs = []
    for dy, dx in _NEIGHBOURS:
        yy, xx = y + dy, x + dx
        ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        if cell is not None:
            ok &= (torch.div(yy, cell, rounding_mode="floor") == torch.div(y, cell, rounding_mode="floor"))
            ok &= (torch.div(xx, cell, rounding_mode="floor") == torch.div(x, cell, rounding_mode="floor"))
        q = plane * (h * w) + yy.clamp(0, h - 1) * w + xx.clamp(0, w - 1)
        nb = idmap[q]
        nbrs.append(torch.where(ok & (nb >= 0), nb, ids))
    nb = torch.stack(nbrs, 1).view(-1)  # (E * 8,), self where there is no neighbour
    # FastSV-style iteration (hooking + shortcutting) on float labels (exact below 2^24)
    ftype = torch.float32 if e < (1 << 24) else torch.float64
    lab = ids.to(ftype)
    for _ in range(max_iter):
        m = lab.index_select(0, nb).view(e, 8).amin(1)  # smallest neighbour label
        parent = lab.long()
        new = lab.scatter_reduce(0, parent, m, "amin")  # hook each root to it
        new = torch.minimum(new, m)
        new = new.index_select(0, new.long())  # shortcut
        if torch.equal(new, lab):
            break
        lab = new
    lab = lab.long()
    out[pix] = pix[lab]
    return out.view(n, h, w)


def _stats(labels: Tensor, mag: Tensor, xs: Tensor, ys: Tensor, per_image: int) -> EdgeGroups:
    """Group statistics from flat labels (root index per foreground pixel)."""
    fg = labels >= 0
    root = labels[fg]
    numel = labels.numel()
    dev = labels.device
    # float64: sums of float32 magnitudes >= the edge threshold are exact, so the same in
    # any order (a batch or one image alone gives the same groups)
    mass = torch.zeros(numel, dtype=torch.float64, device=dev).index_add_(0, root, mag[fg].double())
    big = torch.iinfo(torch.long).max
    x = xs[fg]
    y = ys[fg]
    x1 = torch.full((numel,), big, dtype=torch.long, device=dev).scatter_reduce_(0, root, x, "amin")
    y1 = torch.full((numel,), big, dtype=torch.long, device=dev).scatter_reduce_(0, root, y, "amin")
    x2 = torch.full((numel,), -1, dtype=torch.long, device=dev).scatter_reduce_(0, root, x, "amax")
    y2 = torch.full((numel,), -1, dtype=torch.long, device=dev).scatter_reduce_(0, root, y, "amax")
    ids = torch.nonzero(x2 >= 0).squeeze(1)
    return EdgeGroups(
        batch=torch.div(ids, per_image, rounding_mode="floor"),
        x1=x1[ids], y1=y1[ids], x2=x2[ids], y2=y2[ids], magnitude=mass[ids],
    )


@numba.njit(cache=True, nogil=True)
def _find(parent: np.ndarray, p: int) -> int:  # pragma: no cover - compiled
    while parent[p] != p:
        parent[p] = parent[parent[p]]  # path halving
        p = parent[p]
    return p


@numba.njit(cache=True, nogil=True, inline="always")
def _union(parent: np.ndarray, p: int, q: int) -> None:  # pragma: no cover - compiled
    """Join the sets of ``p`` and ``q``; the smaller root becomes the root of both."""
    a = _find(parent, p)
    c = _find(parent, q)
    if a < c:
        parent[c] = a
    elif c < a:
        parent[a] = c


@numba.njit(cache=True, nogil=True)
def _union_pass(edges: np.ndarray, cell: int) -> np.ndarray:  # pragma: no cover - compiled
    """Union–find over the edge pixels (``edges > 0``; NaN is background) of ``(B, H, W)`` in
    raster order: 8-connected, not across images nor ``cell`` tiles (``cell <= 0``: no
    tiles). Returns the parent of every pixel, ``int64 [B·H·W]`` (−1: no edge); each
    component's root is its smallest flat index."""
    b, h, w = edges.shape
    n = b * h * w
    flat = edges.reshape(-1)
    parent = np.full(n, -1, np.int64)
    # which neighbours share a tile, per column (left, right) and per row (above): the
    # same tests as ``yy // cell == y // cell`` and ``xx // cell == x // cell``, made once
    left_ok = np.ones(w, np.bool_)
    right_ok = np.ones(w, np.bool_)
    left_ok[0] = False
    right_ok[w - 1] = False
    if cell > 0:
        for x in range(w):
            if x % cell == 0:
                left_ok[x] = False
            if (x + 1) % cell == 0:
                right_ok[x] = False
    for i in range(b):
        for y in range(h):
            up = y > 0 and (cell <= 0 or y % cell != 0)
            row = (i * h + y) * w
            for x in range(w):
                p = row + x
                if not flat[p] > 0:
                    continue
                parent[p] = p
                if up:
                    q = p - w
                    if left_ok[x] and parent[q - 1] >= 0:  # (-1, -1)
                        _union(parent, p, q - 1)
                    if parent[q] >= 0:  # (-1, 0)
                        _union(parent, p, q)
                    if right_ok[x] and parent[q + 1] >= 0:  # (-1, +1)
                        _union(parent, p, q + 1)
                if left_ok[x] and parent[p - 1] >= 0:  # (0, -1)
                    _union(parent, p, p - 1)
    return parent


@numba.njit(cache=True, nogil=True)
def _connected_groups_kernel(edges: np.ndarray, cell: int):  # pragma: no cover - compiled
    """The components of :func:`_union_pass`, in the order of their roots, with their
    statistics as :func:`_stats` computes them (float64 mass, inclusive bounds)."""
    b, h, w = edges.shape
    n = b * h * w
    flat = edges.reshape(-1)
    parent = _union_pass(edges, cell)
    # one raster pass numbers the groups and sums them: a root (its group's smallest index)
    # comes before the rest of its group, and is marked with its number as −2 − number
    m = 0
    for p in range(n):
        m += parent[p] >= 0
    batch, x1, y1 = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.int64)
    x2, y2 = np.empty(m, np.int64), np.empty(m, np.int64)
    mass = np.zeros(m, np.float64)
    count = 0
    for i in range(b):
        for y in range(h):
            row = (i * h + y) * w
            for x in range(w):
                p = row + x
                q = parent[p]
                if q == -1:
                    continue
                if q == p:  # a root: a new group
                    g = count
                    parent[p] = -2 - g
                    count += 1
                    batch[g], x1[g], y1[g], x2[g], y2[g] = i, x, y, x, y
                else:
                    while parent[q] >= 0:
                        q = parent[q]
                    g = -2 - parent[q]
                    parent[p] = q  # (q is numbered; later pixels that point at p go straight there)
                    x1[g] = min(x1[g], x)
                    y1[g] = min(y1[g], y)
                    x2[g] = max(x2[g], x)
                    y2[g] = max(y2[g], y)
                mass[g] += np.float64(flat[p])
    return batch[:count], x1[:count], y1[:count], x2[:count], y2[:count], mass[:count]


def connected_groups(edges: Tensor, cell: int | None = None) -> EdgeGroups:
    """8-connected groups of the edge pixels (``edges > 0``) of ``(B, H, W)`` magnitudes.

    With ``cell`` set, components are cut at the borders of ``cell × cell`` tiles. On the
    CPU a compiled union–find (numba) labels them in one raster pass; elsewhere
    :func:`label_components` (FastSV as tensor ops). Both give the same groups, in the
    same order (by each component's first pixel in raster order).
    """
    b, h, w = edges.shape
    if edges.device.type == "cpu" and edges.dtype in (torch.float32, torch.float64):
        e, c = edges.contiguous().numpy(), 0 if cell is None else int(cell)
        parts: dict[int, tuple] = {}

        if b == 1 and c > 0 and h >= 2 * c:
            return _one_image_in_two(e, c)

        def run(lo: int, hi: int) -> None:
            parts[lo] = _connected_groups_kernel(e[lo:hi], c)

        on_two_cores(run, b)  # images are independent: halves in order, batch index shifted
        return _joined([parts[lo] for lo in sorted(parts)], [(lo, 0) for lo in sorted(parts)])
    xs, ys = _coords(b, h, w, edges.device)
    labels = label_components(edges > 0, cell).view(-1)
    return _stats(labels, edges.reshape(-1), xs.reshape(-1), ys.reshape(-1), h * w)


def _one_image_in_two(e: np.ndarray, cell: int) -> EdgeGroups:
    """:func:`connected_groups` of one image ``(1, H, W)`` with tiles, its top and bottom
    rows on two cores, cut at a tile border: no group crosses one, every root above the
    cut precedes every root below it in raster order, and each group's pixels are summed
    in the same order, so the groups, their order and their masses are the same."""
    h = e.shape[1]
    cut = (h // 2) // cell * cell
    spans = [(0, cut), (cut, h)]
    parts: list[tuple | None] = [None, None]

    def run(lo: int, hi: int) -> None:
        for j in range(lo, hi):
            parts[j] = _connected_groups_kernel(e[:, spans[j][0]: spans[j][1]], cell)

    on_two_cores(run, 2)
    return _joined(parts, [(0, spans[j][0]) for j in (0, 1)])  # the rows below the cut shifted down


def _joined(parts: list, shifts: list[tuple[int, int]]) -> EdgeGroups:
    """:class:`EdgeGroups` of the kernel's outputs ``(batch, x1, y1, x2, y2, mass)`` for
    consecutive parts, each part's batch index and rows shifted by its ``shifts`` entry
    (in numpy: torch's small ops cost several times as much per call)."""
    cols = []
    for i in range(6):
        add = [s[0] if i == 0 else s[1] if i in (2, 4) else 0 for s in shifts]
        cols.append(torch.from_numpy(np.concatenate([p[i] + a if a else p[i] for p, a in zip(parts, add)])))
    return EdgeGroups(*cols)
