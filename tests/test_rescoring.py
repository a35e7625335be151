"""The second scoring pass (ReebConfig.rescore): the cues against brute-force references on
tiny hand-made maps, 'none' leaves the default as it is, both scoring paths agree, and bad
settings are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.config import TRAINING_FREE
from reeb_torch.selection import WindowSelection
from reeb_torch.stages.groups import connected_groups
from reeb_torch.stages.rescoring import (affinity_cue, apply_cue, contrast_cue, density_cue, group_graph,
                                         orientation_cue, top_candidates)
from reeb_torch.stages.scoring import integral_image


def _edge_map(seed: int, h: int, w: int, density: float = 0.25) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    e = torch.rand(1, h, w, generator=g)
    return torch.where(torch.rand(1, h, w, generator=g) < density, 0.1 + 0.9 * e, torch.zeros(1))


def _random_boxes(seed: int, h: int, w: int, k: int, side: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randint(0, w - side + 1, (k,), generator=g)
    y0 = torch.randint(0, h - side + 1, (k,), generator=g)
    x1 = torch.minimum(x0 + side + torch.randint(0, 12, (k,), generator=g), torch.tensor(w))
    y1 = torch.minimum(y0 + side + torch.randint(0, 12, (k,), generator=g), torch.tensor(h))
    return torch.stack([x0, y0, x1, y1], 1)


# -- brute force: pixels, groups and chains in plain Python ------------------------------------
def _reference_groups(edges: np.ndarray, cell: int):
    """Groups by flood fill (8-connected within a tile): the label image, each group's
    pixels (x, y), centroid and principal-axis angle."""
    h, w = edges.shape
    lab = -np.ones((h, w), int)
    groups: list[list[tuple[int, int]]] = []
    for y in range(h):
        for x in range(w):
            if edges[y, x] > 0 and lab[y, x] < 0:
                stack, pix = [(y, x)], []
                lab[y, x] = len(groups)
                while stack:
                    cy, cx = stack.pop()
                    pix.append((cy, cx))
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            yy, xx = cy + dy, cx + dx
                            if (0 <= yy < h and 0 <= xx < w and edges[yy, xx] > 0 and lab[yy, xx] < 0
                                    and yy // cell == cy // cell and xx // cell == cx // cell):
                                lab[yy, xx] = len(groups)
                                stack.append((yy, xx))
                groups.append(pix)
    n = len(groups)
    pts = [np.array([(x, y) for y, x in p], float) for p in groups]
    cen = [p.mean(0) for p in pts]
    theta = []
    for p, c in zip(pts, cen):
        d = p - c
        theta.append(0.5 * math.atan2(2 * (d[:, 0] * d[:, 1]).mean(), (d[:, 0] ** 2).mean() - (d[:, 1] ** 2).mean()))
    return lab, groups, pts, cen, theta


def _reference_cue(edges: np.ndarray, box: tuple[int, int, int, int], cell: int) -> float:
    """Σ w_n m_n / Σ m_n from the pixels: orientation from each group's pixel covariance,
    affinities between groups with pixels within 2 px, w_n = 1 − the best chain product
    (Bellman–Ford over the groups inside)."""
    lab, groups, pts, cen, theta = _reference_groups(edges, cell)
    n = len(groups)
    mass = [sum(float(edges[y, x]) for y, x in p) for p in groups]
    x0, y0, x1, y1 = box
    inside = [all(x0 <= x < x1 and y0 <= y < y1 for x, y in p) for p in pts]
    cut = [not inside[i] and any(x0 <= x < x1 and y0 <= y < y1 for x, y in pts[i]) for i in range(n)]

    def aff(i: int, j: int) -> float:
        if np.abs(pts[i][:, None, :] - pts[j][None, :, :]).max(2).min() > 2:
            return 0.0
        d = cen[j] - cen[i]
        tij = math.atan2(d[1], d[0])
        return abs(math.cos(theta[i] - tij) * math.cos(theta[j] - tij)) ** 2

    best = [1.0 if cut[i] else 0.0 for i in range(n)]
    for _ in range(n):
        for i in range(n):
            if best[i] == 0.0:
                continue
            for j in range(n):
                if inside[j] and j != i:
                    v = best[i] * aff(i, j)
                    if v >= 0.05 and v > best[j]:
                        best[j] = v
    total = sum(m for m, ins in zip(mass, inside) if ins)
    kept = sum(m * (1 - best[i]) for i, (m, ins) in enumerate(zip(mass, inside)) if ins)
    return kept / total if total > 0 else 1.0


def _enclosed(edges: torch.Tensor, boxes: torch.Tensor, cell: int) -> torch.Tensor:
    g = connected_groups(edges, cell)
    out = []
    for x0, y0, x1, y1 in boxes.tolist():
        m = (g.x1 >= x0) & (g.y1 >= y0) & (g.x2 < x1) & (g.y2 < y1)
        out.append(float(g.magnitude[m].sum()))
    return torch.tensor(out, dtype=torch.float64)


def test_affinity_on_hand_made_lines():
    """A straight line cut by the box's border is chained out of it (nothing survives); a
    line wholly inside survives; a line at right angles to the cut one only partly."""
    e = torch.zeros(1, 24, 40)
    e[0, 6, 0:30] = 0.5  # horizontal, leaves the box on the left
    e[0, 16, 12:30] = 0.5  # horizontal, wholly inside
    boxes = torch.tensor([[4, 2, 34, 12], [4, 12, 34, 22], [4, 2, 34, 22]])
    bi = torch.zeros(3, dtype=torch.long)
    cue = affinity_cue(e, _enclosed(e, boxes, 8), boxes, bi, 8)
    assert float(cue[0]) == pytest.approx(0.0, abs=1e-12)
    assert float(cue[1]) == pytest.approx(1.0)
    assert 0.3 < float(cue[2]) < 0.7  # the enclosed line survives, the cut one does not
    for k in range(3):
        assert float(cue[k]) == pytest.approx(_reference_cue(e[0].numpy(), tuple(boxes[k].tolist()), 8), abs=1e-9)


def test_affinity_matches_brute_force():
    e = _edge_map(3, 26, 34, 0.2)
    boxes = _random_boxes(4, 26, 34, 25, 9)
    cue = affinity_cue(e, _enclosed(e, boxes, 8), boxes, torch.zeros(len(boxes), dtype=torch.long), 8)
    for k in range(len(boxes)):
        assert float(cue[k]) == pytest.approx(_reference_cue(e[0].numpy(), tuple(boxes[k].tolist()), 8), abs=1e-9)
    assert float(cue.min()) < 0.99  # the example does chain some mass out


def test_orientation_spread():
    """One direction: no spread; as much vertical as horizontal edge: full spread; and
    random maps against the pixels' sums."""
    e = torch.zeros(1, 24, 40)
    e[0, 2:20, 10] = 0.5  # a pole
    e[0, 2:19, 25] = 0.5  # and a cross bar of the same length apart from it
    e[0, 21, 22:39] = 0.5
    boxes = torch.tensor([[5, 0, 16, 24], [20, 0, 40, 24], [0, 0, 2, 2]])
    got = orientation_cue(e, boxes, torch.zeros(3, dtype=torch.long), 8)
    assert got.tolist() == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)
    e = _edge_map(8, 22, 31, 0.2)
    boxes = _random_boxes(9, 22, 31, 20, 6)
    got = orientation_cue(e, boxes, torch.zeros(len(boxes), dtype=torch.long), 8)
    lab, _, _, _, theta = _reference_groups(e[0].numpy(), 8)
    for k, (x0, y0, x1, y1) in enumerate(boxes.tolist()):
        c = s = m = 0.0
        for y in range(y0, y1):
            for x in range(x0, x1):
                if lab[y, x] >= 0:
                    v = float(e[0, y, x])
                    m += v
                    c += v * math.cos(2 * theta[lab[y, x]])
                    s += v * math.sin(2 * theta[lab[y, x]])
        assert float(got[k]) == pytest.approx(1 - math.hypot(c, s) / m if m > 0 else 0.0, abs=1e-9)


def test_group_graph_has_the_scoring_groups():
    e = _edge_map(5, 30, 45)
    label, mass, bounds, start, nbr, aff = group_graph(e[0].numpy(), 8)
    g = connected_groups(e, 8)
    assert np.array_equal(mass, g.magnitude.numpy())
    assert np.array_equal(bounds, torch.stack([g.x1, g.y1, g.x2, g.y2], 1).numpy())
    assert ((aff >= 0) & (aff <= 1)).all() and len(nbr) == start[-1]


def test_density_and_contrast_match_sums():
    e = _edge_map(6, 20, 30)
    boxes = _random_boxes(7, 20, 30, 30, 5)
    bi = torch.zeros(len(boxes), dtype=torch.long)
    ii = integral_image(e)
    dens, con = density_cue(ii, boxes, bi), contrast_cue(ii, boxes, bi)
    a = e[0].double()
    for k, (x0, y0, x1, y1) in enumerate(boxes.tolist()):
        w, h = x1 - x0, y1 - y0
        inner = a[y0:y1, x0:x1]
        assert float(dens[k]) == pytest.approx(float(inner.mean()))
        mx, my = max(1, int(math.floor(w / 4 + 0.5))), max(1, int(math.floor(h / 4 + 0.5)))
        outer = a[max(0, y0 - my): y1 + my, max(0, x0 - mx): x1 + mx]
        n_ring = outer.numel() - inner.numel()
        ring = (float(outer.sum()) - float(inner.sum())) / n_ring if n_ring else 0.0
        assert float(con[k]) == pytest.approx((float(inner.mean()) + 1e-3) / (ring + 1e-3))


def test_top_candidates_and_scope():
    scores = torch.tensor([[0.5, 0.9, 0.1, 0.9, 0.3]])
    chosen = torch.tensor([[True, True, False, True, True]])
    (idx,) = top_candidates(scores, chosen, 3)
    assert idx.tolist() == [1, 3, 0]  # ties: lower index first
    cue = torch.tensor([2.0, 1.0, 3.0], dtype=torch.float64)
    out = apply_cue(scores, [idx], [cue], [torch.tensor([True, True, False])], 1.0)
    assert out[0].tolist() == pytest.approx([0.5, 0.9 * 2 / 1.5, 0.1, 0.9 / 1.5, 0.3])
    assert scores[0, 1] == pytest.approx(0.9)  # a new tensor


def test_none_is_the_default_bit_for_bit(sample_image):
    base = ProposalGenerator(**TRAINING_FREE)([sample_image])[0]
    other = ProposalGenerator(ReebConfig(**TRAINING_FREE, rescore="none", rescore_top=5, rescore_power=3.0,
                                         rescore_scope="persons"))([sample_image])[0]
    assert torch.equal(base["boxes"], other["boxes"]) and torch.equal(base["scores"], other["scores"])
    r = WindowSelection(ReebConfig())
    s, c = torch.rand(1, 4), torch.ones(1, 4, dtype=torch.bool)
    assert r.rescore(None, None, s, c) == (s, c)  # type: ignore[arg-type]


@pytest.mark.parametrize("cue", ["affinity", "density", "contrast", "orientation"])
def test_cues_change_the_ranking_and_both_paths_agree(sample_image, cue, monkeypatch):
    cfg = ReebConfig(**TRAINING_FREE, rescore=cue, rescore_top=3000)
    got = ProposalGenerator(cfg)([sample_image])[0]
    base = ProposalGenerator(**TRAINING_FREE)([sample_image])[0]
    assert not torch.equal(got["boxes"], base["boxes"])
    assert bool((got["scores"][:-1] >= got["scores"][1:]).all())
    monkeypatch.setattr(WindowSelection, "compiled_scoring_applies", lambda self, maps, grid: False)
    torch_path = ProposalGenerator(cfg)([sample_image])[0]
    assert torch.equal(got["boxes"], torch_path["boxes"]) and torch.equal(got["scores"], torch_path["scores"])


def test_persons_scope_leaves_wide_windows_alone(sample_image):
    cut = ProposalGenerator(**TRAINING_FREE, rescore="density", rescore_power=0.0)([sample_image])[0]
    got = ProposalGenerator(**TRAINING_FREE, rescore="density", rescore_scope="persons")([sample_image])[0]
    wide = lambda r: {tuple(b) for b, s in zip(r["boxes"].tolist(), r["scores"].tolist())  # noqa: E731
                      if b[2] - b[0] >= 0.8 * (b[3] - b[1]) + 2}
    common = wide(cut) & wide(got)
    assert common and len(common) > 0.5 * len(wide(cut))


def test_persons_scope_by_shape_and_real_height():
    hk = 100  # horizon row 47 with the default horizon 0.47
    boxes = torch.tensor([[0, 40, 10, 60], [0, 40, 30, 60], [0, 10, 10, 60], [0, 10, 10, 40]])
    shape = WindowSelection(ReebConfig(**TRAINING_FREE, rescore="density", rescore_scope="persons"))._rescore_scope(boxes, hk)
    assert shape.tolist() == [True, False, True, True]
    tall = WindowSelection(ReebConfig(**TRAINING_FREE, rescore="density", rescore_scope="persons", rescore_max_height_m=2.3))
    # 20 px over 13 rows below the horizon: 2.54 m; 50 over 13: 6.3 m; above the horizon: no
    assert tall._rescore_scope(boxes, hk).tolist() == [False, False, False, False]
    boxes = torch.tensor([[0, 70, 10, 90]])  # 20 px over 43 rows: 0.77 m
    assert tall._rescore_scope(boxes, hk).tolist() == [True]
    assert WindowSelection(ReebConfig(**TRAINING_FREE, rescore="density"))._rescore_scope(boxes, hk).tolist() == [True]


@pytest.mark.parametrize("changes, words", [
    (dict(rescore="edges"), "ReebConfig.rescore"),
    (dict(rescore_top=0), "ReebConfig.rescore_top must be >= 1"),
    (dict(rescore_power=-1.0), "ReebConfig.rescore_power"),
    (dict(rescore_scope="cars"), "ReebConfig.rescore_scope"),
    (dict(rescore_thin=0.0), "ReebConfig.rescore_thin"),
    (dict(rescore_max_height_m=0.0), "ReebConfig.rescore_max_height_m"),
    (dict(rescore="density", refine=True), "refine"),
    (dict(rescore="affinity", grouping="cell"), "grouping='connected'"),
    (dict(rescore="orientation", grouping="cell"), "grouping='connected'"),
])
def test_bad_settings_are_refused(changes, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
        ReebConfig(**changes)


@pytest.mark.parametrize("n", [0, 1, 9, 5000])
def test_descending_stable_is_torchs_stable_sort(n: int) -> None:
    """The key sort of ``top_candidates`` gives torch's stable descending permutation, with
    ties, ±0, ±inf and subnormals; NaN falls back to torch's sort."""
    from reeb_torch.stages.rescoring import _descending_stable

    g = torch.Generator().manual_seed(n)
    v = (torch.randn(n, generator=g) * 4).round() / 3
    if n > 8:
        v[::3] = -0.0
        v[1::5] = 0.0
        v[2], v[4], v[5], v[7] = math.inf, -math.inf, -1e-45, 1e-45
    assert torch.equal(_descending_stable(v), v.sort(descending=True, stable=True).indices)
    w = torch.tensor([1.0, math.nan, 2.0, 1.0])
    assert torch.equal(_descending_stable(w), w.sort(descending=True, stable=True).indices)
    # the first `top` of it by radix selection and sort (ties at the cut included)
    from reeb_torch.stages.rescoring import _top_stable

    full = v.sort(descending=True, stable=True).indices
    for top in (1, 2, 7, max(n - 1, 1), n + 3):
        assert torch.equal(_top_stable(v, top), full[:top]), top
    assert torch.equal(_top_stable(w, 2), w.sort(descending=True, stable=True).indices[:2])
