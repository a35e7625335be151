"""Edge Boxes' refinement: exact enclosed sums at arbitrary boxes, the box scorer agrees
with the grid's scores, and the compiled refinement with the tensor one."""

from __future__ import annotations

import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.config import TRAINING_FREE
from reeb_torch.stages.groups import EdgeGroups
from reeb_torch.stages.refinement import enclosed_at, enclosed_tables, refine_boxes


def _random_groups(seed: int, b: int, h: int, w: int, n: int, ext: int) -> EdgeGroups:
    g = torch.Generator().manual_seed(seed)
    x1 = torch.randint(0, w, (n,), generator=g)
    y1 = torch.randint(0, h, (n,), generator=g)
    x2 = (x1 + torch.randint(0, ext + 1, (n,), generator=g)).clamp(max=w - 1)
    y2 = (y1 + torch.randint(0, ext + 1, (n,), generator=g)).clamp(max=h - 1)
    return EdgeGroups(torch.randint(0, b, (n,), generator=g), x1, y1, x2, y2, torch.rand(n, generator=g))


def test_enclosed_at_matches_brute_force():
    b, h, w = 2, 37, 53
    groups = _random_groups(0, b, h, w, 400, 7)
    t = enclosed_tables(groups, b, h, w)
    g = torch.Generator().manual_seed(1)
    k = 1500
    side = t.max_extent + 1
    x0 = torch.randint(0, w - side + 1, (k,), generator=g)
    y0 = torch.randint(0, h - side + 1, (k,), generator=g)
    x1 = torch.minimum(x0 + side + torch.randint(0, 30, (k,), generator=g), torch.tensor(w))
    y1 = torch.minimum(y0 + side + torch.randint(0, 30, (k,), generator=g), torch.tensor(h))
    bi = torch.randint(0, b, (k,), generator=g)
    got = enclosed_at(t, bi, x0, y0, x1, y1)
    m = groups.magnitude.double()
    for i in range(k):
        inside = ((groups.batch == bi[i]) & (groups.x1 >= x0[i]) & (groups.y1 >= y0[i])
                  & (groups.x2 < x1[i]) & (groups.y2 < y1[i]))
        assert abs(float(got[i]) - float(m[inside].sum())) < 1e-9


def test_refine_climbs_to_the_best_box():
    # score = −distance of the box to a target box: refinement must reach it exactly
    target = torch.tensor([10, 12, 40, 30])

    def score(boxes, bi):
        return -(boxes - target).abs().sum(1).double()

    start = torch.tensor([[4, 4, 48, 36], [16, 16, 30, 26]])
    out, sc = refine_boxes(start, torch.zeros(2, dtype=torch.long), score, 64, 48, 4, 0.6)
    assert out[0].tolist() == target.tolist() and float(sc[0]) == 0.0
    # one move per side and step size (as Edge Boxes): x2 of the small box can climb
    # 4 + 2 + 1 pixels of the 10 it needs, and the score only goes up
    assert out[1].tolist() == [10, 12, 37, 30]
    assert float(sc[1]) == -3.0 > float(score(start[1:], None)[0])


def test_box_scorer_equals_grid_scores(sample_image):
    gen = ProposalGenerator(ReebConfig(**TRAINING_FREE, refine=True, straddle_weight=0.5, road_score="stand"))
    seen = {}
    real = gen.selection.refine

    def spy(maps, grid, chosen, scores):
        fn, side = gen.selection.box_scorer(maps)
        bi, ni = torch.nonzero(chosen, as_tuple=True)
        boxes = grid.boxes[ni].round().long()
        ok = ((boxes[:, 2:] - boxes[:, :2]) >= side).all(1)
        seen["got"] = fn(boxes[ok], bi[ok])
        seen["ref"] = scores[bi, ni][ok].double()
        return real(maps, grid, chosen, scores)

    gen.selection.refine = spy  # type: ignore[method-assign]
    out = gen([sample_image])[0]
    assert seen["got"].numel() > 1000
    torch.testing.assert_close(seen["got"], seen["ref"], rtol=1e-4, atol=1e-7)
    assert (out["scores"][:-1] >= out["scores"][1:]).all()


def test_enclosed_grid_equals_the_per_size_scatter(sample_image):
    # the tensor path's enclosed sums (prefix tables + strided slices) are the very same
    # float64 numbers as the per-size scatter of scoring.enclosed_sums; a road term keeps
    # the generator on the tensor path (the compiled pass reads the same tables)
    from reeb_torch.stages import scoring

    gen = ProposalGenerator(road_score="reward")
    seen = {}
    real = gen.selection.enclosed

    def spy(maps, grid):
        out = real(maps, grid)
        ref = scoring.enclosed_sums(maps.groups, maps.edges.shape[0], grid.sizes)
        seen["n"] = len(out)
        seen["equal"] = all(torch.equal(x, y) for x, y in zip(out, ref))
        return out

    gen.selection.enclosed = spy  # type: ignore[method-assign]
    gen([sample_image[:, :200, :600]])
    assert seen["n"] > 50 and seen["equal"]


def test_compiled_tables_equal_the_tensor_tables(sample_image):
    # the CPU kernel fills the very same float64 tables as the tensor scatters + cumsums
    from reeb_torch.stages import edges as E
    from reeb_torch.stages.groups import connected_groups
    from reeb_torch.stages.refinement import _enclosed_tables_torch, enclosed_tables

    gen = torch.Generator().manual_seed(5)
    crops = torch.stack([sample_image[:, :180, :500], sample_image[:, 100:280, 300:800]]).float() / 255
    e = E.edge_map(E.to_gray(crops), 1.0, 0.05, True, True)
    rnd = torch.rand(3, 31, 45, generator=gen) * (torch.rand(3, 31, 45, generator=gen) < 0.4)
    empty = torch.zeros(2, 20, 30)
    for edges, cell in ((e, 8), (e, None), (rnd, 5), (empty, 8)):
        g = connected_groups(edges, cell)
        b, h, w = edges.shape
        got, ref = enclosed_tables(g, b, h, w), _enclosed_tables_torch(g, b, h, w)
        assert got.max_extent == ref.max_extent
        for f in ("anchor", "cut_col", "cut_row", "corner"):
            assert torch.equal(getattr(got, f), getattr(ref, f)), f


@pytest.mark.parametrize("overrides", [
    {},  # the package default: vegetation, shadow (square root), class location score
    dict(shadow_score="none", vegetation_score="none", location_score="ground", road_score="flat"),
    dict(score_norm="area", location_score="none", center_fraction=0.4, vegetation_box=0.9, vegetation_power=2),
])
def test_compiled_refinement_equals_the_tensor_refinement(sample_image, overrides):
    # the compiled pass makes the very same moves and scores, bit for bit, as the tensor
    # scorer's refine_boxes (same float64 operations; the location score and the
    # normaliser are tabulated by the tensor functions themselves)
    gen = ProposalGenerator(ReebConfig(**TRAINING_FREE, refine=True, **overrides))
    ranking = gen.selection
    seen = {}
    real = ranking.refine

    def spy(maps, *args):
        assert ranking.compiled_refine_applies(maps)
        seen["compiled"] = real(maps, *args)
        ranking.compiled_refine_applies = lambda *a: False  # type: ignore[method-assign]
        try:
            seen["tensor"] = real(maps, *args)
        finally:
            del ranking.compiled_refine_applies
        return seen["compiled"]

    ranking.refine = spy  # type: ignore[method-assign]
    gen([sample_image])
    (cb, cs), (tb, ts) = seen["compiled"], seen["tensor"]
    assert cb[0].shape[0] > 1000
    moved = (cb[0] != tb[0]).any(1)
    assert not moved.any() and torch.equal(cs[0], ts[0])


@pytest.mark.parametrize("overrides", [dict(straddle_weight=0.5), dict(road_score="stand"),
                                       dict(location_score="paper"), dict(shadow_power=0.25)])
def test_refinement_of_other_scores_takes_the_tensor_path(overrides):
    from reeb_torch.selection import ScoreMaps
    from reeb_torch.stages.groups import connected_groups

    gen = ProposalGenerator(ReebConfig(**TRAINING_FREE, refine=True, **overrides))
    crossing = (torch.zeros(1), torch.zeros(1)) if overrides.get("straddle_weight") else None
    edges = torch.zeros(1, 4, 4)
    maps = ScoreMaps(edges, connected_groups(edges, 8), (4, 4), crossing=crossing)
    assert not gen.selection.compiled_refine_applies(maps)


def test_refine_min_aspect_keeps_narrow_boxes_where_they_are(sample_image):
    seen = {}
    for aspect in (0.0, 0.6):
        gen = ProposalGenerator(ReebConfig(**TRAINING_FREE, refine=True, refine_min_aspect=aspect))
        real = gen.selection.refine

        def spy(maps, grid, chosen, scores):
            out = real(maps, grid, chosen, scores)
            ni = torch.nonzero(chosen[0]).squeeze(1)
            seen[aspect] = (grid.boxes[ni].round(), out[0][0])
            return out

        gen.selection.refine = spy  # type: ignore[method-assign]
        gen([sample_image])
    start, moved_all = seen[0.0]
    start6, moved6 = seen[0.6]
    assert torch.equal(start, start6)
    narrow = (start[:, 2] - start[:, 0]) < 0.6 * (start[:, 3] - start[:, 1])
    changed_all = (moved_all != start).any(1)
    changed6 = (moved6 != start).any(1)
    assert narrow.any() and (changed_all & narrow).any()  # refining every box moves narrow ones too
    assert not (changed6 & narrow).any()  # with 0.6 they stay
    assert torch.equal(moved6[~narrow], moved_all[~narrow])  # the others move as before
