"""A second, richer scoring pass over the best candidates (``ReebConfig.rescore``; not in the paper).

The grid score V (eq. 12) is cheap enough for every window. After the region cut, the best
``rescore_top`` candidates of each image are scored again with a cue too costly for every
window, and ranked on ``V · f^p`` (``p = rescore_power``), where ``f`` is the cue divided by
its mean over the rescored windows of that image (so ``f`` is 1 on average and windows
outside the pass, or outside ``rescore_scope``, keep a comparable score):

* ``affinity``: Edge Boxes' affinity-weighted ``w_n`` for real (Zitnick & Dollár, ECCV 2014,
  Sec. 3.1). Groups (8-connected edge pixels cut at ``group_cell`` tiles, as eq. 1's groups)
  get an orientation (the principal axis of their pixels, the tangent of the contour piece)
  and a centroid; two groups within ``radius`` pixels have the affinity
  ``a(i, j) = |cos(θ_i − θ_ij) · cos(θ_j − θ_ij)|^2`` (θ_ij the angle between their
  centroids). A group inside a box gets ``w_n = 1 − max_path Π a`` over the chains of groups
  inside the box that start at a group cut by the box's border (chains stop below 0.05).
  The cue is the share of the enclosed edge mass that survives: ``Σ w_n m_n / Σ m_n``.
  Compiled (numba, CPU; the edge map is read on the CPU on any device): per box, a
  max-product search from the groups on the box's inner border.
* ``density``: the box's mean edge magnitude (textured objects against smooth road and sky).
* ``orientation``: the spread of the edge orientations inside the box, ``1 − |Σ m e^{2iθ}| / Σ m``
  over its edge pixels (θ: the principal axis of each pixel's group, as for ``affinity``;
  compiled labelling, then integral images): a pole, a trunk or a sign post has edges of one
  direction (spread near 0), a person or a rider edges of many.
* ``contrast``: the box's mean edge magnitude over that of the ring around it (a quarter of
  the box's side wide, clipped to the image): an object stands out of its surround.

``density`` and ``contrast`` are tensor ops on the edge map's integral image (any device).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ._radix import descending_order, kth_largest
from ._threads import on_two_cores
from .groups import pixel_labels
from .refinement import box_sum_at

__all__ = ["CUES", "top_candidates", "density_cue", "contrast_cue", "orientation_cue", "group_graph",
           "affinity_cue", "apply_cue"]

CUES = ("none", "affinity", "density", "contrast", "orientation")
"""The values of ``ReebConfig.rescore``."""

_STOP = 0.05
"""Edge Boxes' chains of affinities stop below this product."""

_EPS = 1e-3
"""Added to the mean edge magnitudes of ``contrast`` (magnitudes are in [0, 1])."""


def top_candidates(scores: Tensor, chosen: Tensor, top: int) -> list[Tensor]:
    """Per image, the indices (``int64 [K_i]``, ``K_i <= top``) of its ``top`` best chosen
    windows by ``scores`` (``float32 [B, N]``; ``chosen`` ``bool [B, N]``), best first; ties
    go to the lower window index (a stable sort), so every path picks the same windows."""
    out = []
    for i in range(scores.shape[0]):
        cand = torch.nonzero(chosen[i]).squeeze(1)
        order = _top_stable(scores[i, cand], top)
        out.append(cand[order])
    return out


def _top_stable(vals: Tensor, top: int) -> Tensor:
    """``_descending_stable(vals)[:top]``: on the CPU without NaN, only the values at or
    above the ``top``-th largest (compiled radix selection) are sorted (compiled radix
    sort, stable), the kernels the window NMS uses; they come in index order, so ties keep
    the lower index first, as in the full sort."""
    n = len(vals)
    if (top >= n or vals.device.type != "cpu" or vals.dtype != torch.float32 or not vals.is_contiguous()
            or bool(vals.isnan().any())):
        return _descending_stable(vals)[:top]
    v = vals.numpy()
    sel = np.flatnonzero(v >= kth_largest(v, top))  # the best top and their ties, ascending
    return torch.from_numpy(sel[descending_order(v[sel])][:top])


def _descending_stable(vals: Tensor) -> Tensor:
    """``vals.sort(descending=True, stable=True).indices`` (``float32 [n]``), the same
    permutation: on the CPU without NaN, one sort of distinct ``uint64`` keys (the score's
    bits mapped to an order-preserving integer, ``−0`` as ``+0``, high; the index low),
    about 2.4 times faster than the stable float sort at 30 000 to 170 000 values."""
    if vals.device.type != "cpu" or vals.dtype != torch.float32 or len(vals) >= 2 ** 32 or bool(vals.isnan().any()):
        return vals.sort(descending=True, stable=True).indices
    u = (vals.numpy() + np.float32(0.0)).view(np.uint32)  # + 0: −0 → +0 (they tie in torch's sort)
    up = np.where(u >> 31 != 0, ~u, u | np.uint32(0x80000000))  # ascending as the floats
    key = (~up).astype(np.uint64) << np.uint64(32) | np.arange(len(u), dtype=np.uint64)
    key.sort()
    return torch.from_numpy((key & np.uint64(0xFFFFFFFF)).astype(np.int64))


def density_cue(ii_edges: Tensor, boxes: Tensor, bi: Tensor) -> Tensor:
    """Mean edge magnitude inside each box, ``float64 [K]``. ``ii_edges``: the edge map's
    integral image ``(B, h + 1, w + 1)``; ``boxes``: int64 ``[K, 4]`` working pixels
    ``(x0, y0, x1, y1)``, x1/y1 exclusive, within the image; ``bi``: their images ``[K]``."""
    x0, y0, x1, y1 = boxes.unbind(1)
    area = ((x1 - x0) * (y1 - y0)).clamp(min=1).double()
    return box_sum_at(ii_edges, bi, x0, y0, x1, y1) / area


def contrast_cue(ii_edges: Tensor, boxes: Tensor, bi: Tensor) -> Tensor:
    """``(d_in + ε) / (d_ring + ε)``, ``float64 [K]``: the mean edge magnitude inside each
    box over that of the ring around it, ``round(w / 4)`` columns and ``round(h / 4)`` rows
    wide (at least 1), clipped to the image (a ring wholly outside the image reads
    ``d_ring = 0``). Arguments as :func:`density_cue`."""
    hk, wk = ii_edges.shape[-2] - 1, ii_edges.shape[-1] - 1
    x0, y0, x1, y1 = boxes.unbind(1)
    w, h = x1 - x0, y1 - y0
    mx = torch.div(w + 2, 4, rounding_mode="floor").clamp(min=1)  # round(w / 4), halves up
    my = torch.div(h + 2, 4, rounding_mode="floor").clamp(min=1)
    ox0, oy0 = (x0 - mx).clamp(min=0), (y0 - my).clamp(min=0)
    ox1, oy1 = (x1 + mx).clamp(max=wk), (y1 + my).clamp(max=hk)
    inner = box_sum_at(ii_edges, bi, x0, y0, x1, y1)
    outer = box_sum_at(ii_edges, bi, ox0, oy0, ox1, oy1)
    a_in = (w * h).clamp(min=1).double()
    a_ring = ((ox1 - ox0) * (oy1 - oy0) - w * h).double()
    d_ring = torch.where(a_ring > 0, (outer - inner) / a_ring.clamp(min=1), torch.zeros_like(inner))
    return (inner / a_in + _EPS) / (d_ring + _EPS)


# -- affinity: the groups' graph, then a max-product search per box ----------------------------
@numba.njit(cache=True, nogil=True)
def _label_kernel(edges: np.ndarray, cell: int):  # pragma: no cover - compiled
    """8-connected components of ``edges > 0`` of one ``(h, w)`` image, cut at ``cell`` tiles
    (``cell <= 0``: none), numbered by their first pixel in raster order (as eq. 1's groups:
    :func:`~reeb_torch.stages.groups.pixel_labels`): the label image ``int64 [h·w]`` (−1: no
    edge), and per group its mass, inclusive bounds, centroid and principal-axis angle
    (radians)."""
    h, w = edges.shape
    n = h * w
    flat = edges.reshape(-1)
    label, count = pixel_labels(edges.reshape(1, h, w), cell)
    mass = np.zeros(count)
    bounds = np.empty((count, 4), np.int64)
    bounds[:, 0] = w
    bounds[:, 1] = h
    bounds[:, 2] = -1
    bounds[:, 3] = -1
    mom = np.zeros((count, 6))  # n, Σx, Σy, Σxx, Σyy, Σxy
    for p in range(n):
        g = label[p]
        if g < 0:
            continue
        y, x = p // w, p % w
        mass[g] += np.float64(flat[p])
        bounds[g, 0] = min(bounds[g, 0], x)
        bounds[g, 1] = min(bounds[g, 1], y)
        bounds[g, 2] = max(bounds[g, 2], x)
        bounds[g, 3] = max(bounds[g, 3], y)
        mom[g, 0] += 1.0
        mom[g, 1] += x
        mom[g, 2] += y
        mom[g, 3] += x * x
        mom[g, 4] += y * y
        mom[g, 5] += x * y
    cx = mom[:, 1] / mom[:, 0]
    cy = mom[:, 2] / mom[:, 0]
    theta = np.empty(count)
    for g in range(count):
        sxx = mom[g, 3] / mom[g, 0] - cx[g] * cx[g]
        syy = mom[g, 4] / mom[g, 0] - cy[g] * cy[g]
        sxy = mom[g, 5] / mom[g, 0] - cx[g] * cy[g]
        theta[g] = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    return label, mass, bounds, cx, cy, theta


@numba.njit(cache=True, nogil=True)
def _graph_kernel(label: np.ndarray, h: int, w: int, count: int, cx: np.ndarray, cy: np.ndarray,
                  theta: np.ndarray, radius: int):  # pragma: no cover - compiled
    """The pairs of groups with pixels within ``radius`` (Chebyshev) of each other, both
    ways, as CSR ``(start [G + 1], neighbour [E], affinity [E])``."""
    keys = np.empty(h * w * (2 * radius + 1) * radius + h * w * radius + 1, np.int64)
    k = 0
    for p in range(h * w):
        g = label[p]
        if g < 0:
            continue
        y, x = p // w, p % w
        for dy in range(0, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx <= 0:
                    continue
                yy, xx = y + dy, x + dx
                if yy >= h or xx < 0 or xx >= w:
                    continue
                q = label[yy * w + xx]
                if q < 0 or q == g:
                    continue
                keys[k] = min(g, q) * count + max(g, q)
                k += 1
    pairs = np.unique(keys[:k])
    deg = np.zeros(count + 1, np.int64)
    for key in pairs:
        deg[key // count + 1] += 1
        deg[key % count + 1] += 1
    start = np.cumsum(deg)
    fill = start[:-1].copy()
    nbr = np.empty(2 * len(pairs), np.int64)
    aff = np.empty(2 * len(pairs))
    for key in pairs:
        i, j = key // count, key % count
        dx, dy = cx[j] - cx[i], cy[j] - cy[i]
        tij = math.atan2(dy, dx) if dx != 0.0 or dy != 0.0 else theta[i]
        a = abs(math.cos(theta[i] - tij) * math.cos(theta[j] - tij)) ** 2
        nbr[fill[i]], aff[fill[i]] = j, a
        fill[i] += 1
        nbr[fill[j]], aff[fill[j]] = i, a
        fill[j] += 1
    return start, nbr, aff


@numba.njit(cache=True, nogil=True)
def _inside(bounds: np.ndarray, g: int, x0: int, y0: int, x1: int, y1: int) -> bool:  # pragma: no cover
    return bounds[g, 0] >= x0 and bounds[g, 1] >= y0 and bounds[g, 2] < x1 and bounds[g, 3] < y1


@numba.njit(cache=True, nogil=True)
def _affinity_kernel(boxes: np.ndarray, label: np.ndarray, w: int, mass: np.ndarray, bounds: np.ndarray,
                     start: np.ndarray, nbr: np.ndarray, aff: np.ndarray, out: np.ndarray):  # pragma: no cover
    """``out[k]``: the enclosed mass each box ``(x0, y0, x1, y1)`` loses to its border,
    ``Σ_inside (1 − w_n) m_n`` (the best chain's product times the group's mass)."""
    count = len(mass)
    val = np.zeros(count)
    stamp = np.full(count, -1, np.int64)
    inq = np.zeros(count, np.bool_)
    queue = np.empty(count + 1, np.int64)
    touched = np.empty(count + 1, np.int64)
    for k in range(boxes.shape[0]):
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        head = tail = qn = nt = 0
        for side in range(4):  # the seeds: groups on the inner border that leave the box
            n_side = x1 - x0 if side < 2 else y1 - y0
            for t in range(n_side):
                if side == 0:
                    x, y = x0 + t, y0
                elif side == 1:
                    x, y = x0 + t, y1 - 1
                elif side == 2:
                    x, y = x0, y0 + t
                else:
                    x, y = x1 - 1, y0 + t
                g = label[y * w + x]
                if g < 0 or stamp[g] == k or _inside(bounds, g, x0, y0, x1, y1):
                    continue
                stamp[g] = k
                val[g] = 1.0
                queue[tail] = g
                tail = (tail + 1) % (count + 1)
                qn += 1
                inq[g] = True
        while qn > 0:  # max-product chains into the box (label-correcting search)
            g = queue[head]
            head = (head + 1) % (count + 1)
            qn -= 1
            inq[g] = False
            for e in range(start[g], start[g + 1]):
                j = nbr[e]
                v = val[g] * aff[e]
                if v < _STOP or not _inside(bounds, j, x0, y0, x1, y1):
                    continue
                if stamp[j] != k:
                    stamp[j] = k
                    val[j] = 0.0
                    touched[nt] = j
                    nt += 1
                if v > val[j]:
                    val[j] = v
                    if not inq[j]:
                        inq[j] = True
                        queue[tail] = j
                        tail = (tail + 1) % (count + 1)
                        qn += 1
        lost = 0.0
        for t in range(nt):
            lost += val[touched[t]] * mass[touched[t]]
        out[k] = lost


def _rows_by_image(b_np: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """``(i, rows)`` for each image ``i`` present in ``b_np`` (``int64 [K]``, >= 0), in
    increasing ``i``, ``rows`` its positions ascending (as ``np.nonzero(b_np == i)[0]``):
    one stable argsort instead of a mask per image."""
    order = np.argsort(b_np, kind="stable")
    ends = np.cumsum(np.bincount(b_np))
    starts = ends - np.bincount(b_np)
    return [(int(i), order[starts[i]:ends[i]]) for i in np.flatnonzero(ends - starts)]


def group_graph(edges: np.ndarray, cell: int | None, radius: int = 2) -> tuple[np.ndarray, ...]:
    """The groups of one ``float32 (h, w)`` edge map and their affinity graph:
    ``(label [h·w], mass [G], bounds [G, 4] inclusive x1, y1, x2, y2, start [G + 1],
    neighbour [E], affinity [E])`` (see the module docstring)."""
    h, w = edges.shape
    label, mass, bounds, cx, cy, theta = _label_kernel(np.ascontiguousarray(edges), 0 if cell is None else int(cell))
    start, nbr, aff = _graph_kernel(label, h, w, len(mass), cx, cy, theta, int(radius))
    return label, mass, bounds, start, nbr, aff


def affinity_cue(edges: Tensor, enclosed: Tensor, boxes: Tensor, bi: Tensor, cell: int | None) -> Tensor:
    """``Σ w_n m_n / Σ m_n`` of each box (``float64 [K]`` in [0, 1]; 1 where nothing is
    enclosed), Edge Boxes' affinity-weighted ``w_n``. ``edges``: ``(B, h, w)`` edge map;
    ``enclosed``: ``float64 [K]`` eq. 1's enclosed mass of each box (the same groups);
    ``boxes`` int64 ``[K, 4]`` working pixels (x1, y1 exclusive) of images ``bi``."""
    e = edges.detach().float().cpu().contiguous().numpy()
    bx = boxes.cpu().numpy().astype(np.int64)
    b_np = bi.cpu().numpy()
    lost = np.zeros(len(bx))
    for i, rows in _rows_by_image(b_np):
        label, mass, bounds, start, nbr, aff = group_graph(e[i], cell)
        sub = np.ascontiguousarray(bx[rows])
        part = np.zeros(len(rows))
        on_two_cores(lambda lo, hi: _affinity_kernel(sub[lo:hi], label, e.shape[2], mass, bounds, start, nbr, aff,
                                                     part[lo:hi]), len(rows))
        lost[rows] = part
    lost_t = torch.from_numpy(lost).to(enclosed.device)
    keep = (enclosed - lost_t).clamp(min=0)
    return torch.where(enclosed > 0, keep / enclosed.clamp(min=1e-12), torch.ones_like(enclosed)).clamp(max=1.0)


@numba.njit(cache=True, nogil=True)
def _orientation_sums(label: np.ndarray, edges: np.ndarray, cos2: np.ndarray, sin2: np.ndarray,
                      boxes: np.ndarray, out: np.ndarray):  # pragma: no cover - compiled
    """``out[:, k]``: ``Σ m``, ``Σ m cos 2θ``, ``Σ m sin 2θ`` over box ``k`` of one image, from
    integral images built as ``cumsum`` along x, then along y (the same sums in the same order
    as torch's ``cumsum(3).cumsum(2)``), read as ``ii[y1, x1] − ii[y0, x1] − ii[y1, x0] + ii[y0, x0]``."""
    h, w = edges.shape
    ii = np.zeros((3, h + 1, w + 1))
    for y in range(h):
        a0 = a1 = a2 = 0.0
        for x in range(w):
            g = label[y * w + x]
            if g >= 0:
                m = np.float64(edges[y, x])
                a0 += m
                a1 += m * cos2[g]
                a2 += m * sin2[g]
            else:
                a0 += 0.0
                a1 += 0.0
                a2 += 0.0
            ii[0, y + 1, x + 1] = ii[0, y, x + 1] + a0
            ii[1, y + 1, x + 1] = ii[1, y, x + 1] + a1
            ii[2, y + 1, x + 1] = ii[2, y, x + 1] + a2
    for k in range(boxes.shape[0]):
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        for c in range(3):
            out[c, k] = ii[c, y1, x1] - ii[c, y0, x1] - ii[c, y1, x0] + ii[c, y0, x0]


def orientation_cue(edges: Tensor, boxes: Tensor, bi: Tensor, cell: int | None) -> Tensor:
    """``1 − |Σ m e^{2iθ}| / Σ m`` over the edge pixels of each box, ``float64 [K]`` in [0, 1]
    (0 where a box holds no edge): θ is the principal-axis angle of the pixel's group
    (groups as eq. 1's, cut at ``cell`` tiles). Arguments as :func:`affinity_cue`.
    Compiled (numba, CPU): labelling, then one pass building the integral images of the
    image's boxes and reading them."""
    e = edges.detach().float().cpu().contiguous().numpy()
    bx = boxes.cpu().numpy().astype(np.int64)
    b_np = bi.cpu().numpy()
    sums = np.zeros((3, len(bx)))
    for i, rows in _rows_by_image(b_np):
        label, _, _, _, _, theta = _label_kernel(np.ascontiguousarray(e[i]), 0 if cell is None else int(cell))
        part = np.zeros((3, len(rows)))
        _orientation_sums(label, e[i], np.cos(2 * theta), np.sin(2 * theta), np.ascontiguousarray(bx[rows]), part)
        sums[:, rows] = part
    mass, c, s = torch.from_numpy(sums).unbind(0)
    spread = torch.where(mass > 1e-12, 1.0 - torch.sqrt(c * c + s * s) / mass.clamp(min=1e-12), torch.zeros_like(mass))
    return spread.clamp(0.0, 1.0).to(boxes.device)


def apply_cue(scores: Tensor, idx: list[Tensor], cue: list[Tensor], scope: list[Tensor], power: float) -> Tensor:
    """``scores`` (``float32 [B, N]``, not changed) with each image's windows ``idx[i]`` that
    lie in ``scope[i]`` (bool, same length) multiplied by ``(cue / mean cue)^power`` (the
    mean over those windows; a mean of 0 changes nothing): a new tensor."""
    out = scores.clone()
    for i, (ix, c, sc) in enumerate(zip(idx, cue, scope)):
        if not bool(sc.any()):
            continue
        c = c[sc].double()
        mean = c.mean()
        if not float(mean) > 0:
            continue
        sel = ix[sc]
        out[i, sel] = (out[i, sel].double() * (c / mean) ** power).float()
    return out
