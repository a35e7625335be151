"""Eq. 1's enclosed sums from the prefix tables: exact at arbitrary boxes, the same numbers
as the per-size scatter, and the compiled tables the same as the tensor ones."""

from __future__ import annotations

import torch

from reeb_torch import ProposalGenerator
from reeb_torch.stages.enclosed import enclosed_at, enclosed_tables
from reeb_torch.stages.groups import EdgeGroups


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


def test_enclosed_grid_equals_the_per_size_scatter(sample_image):
    # the tensor path's enclosed sums (prefix tables + strided slices) are the very same
    # float64 numbers as the per-size scatter of scoring.enclosed_sums; a road term keeps
    # the generator on the tensor path (the compiled pass reads the same tables)
    from reeb_torch.stages import scoring

    gen = ProposalGenerator(road_score="reward")
    seen = {}
    real = gen.selection.scoring.enclosed

    def spy(maps, grid):
        out = real(maps, grid)
        ref = scoring.enclosed_sums(maps.groups, maps.edges.shape[0], grid.sizes)
        seen["n"] = len(out)
        seen["equal"] = all(torch.equal(x, y) for x, y in zip(out, ref))
        return out

    gen.selection.scoring.enclosed = spy  # type: ignore[method-assign]
    gen([sample_image[:, :200, :600]])
    assert seen["n"] > 50 and seen["equal"]


def test_compiled_tables_equal_the_tensor_tables(sample_image):
    # the CPU kernel fills the very same float64 tables as the tensor scatters + cumsums
    from reeb_torch.stages import edges as E
    from reeb_torch.stages.groups import connected_groups
    from reeb_torch.stages.enclosed import _enclosed_tables_torch, enclosed_tables

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
