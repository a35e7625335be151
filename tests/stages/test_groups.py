"""Sec. 3.7 edge groups against scipy-free references (a flood fill) on random masks."""

from __future__ import annotations

import torch

from reeb_torch.stages.groups import connected_groups, label_components


def _flood_components(mask: torch.Tensor) -> list[set[tuple[int, int]]]:
    h, w = mask.shape
    seen = torch.zeros_like(mask)
    comps = []
    for y in range(h):
        for x in range(w):
            if mask[y, x] and not seen[y, x]:
                stack, comp = [(y, x)], set()
                seen[y, x] = True
                while stack:
                    cy, cx = stack.pop()
                    comp.add((cy, cx))
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            ny, nx = cy + dy, cx + dx
                            if 0 <= ny < h and 0 <= nx < w and mask[ny, nx] and not seen[ny, nx]:
                                seen[ny, nx] = True
                                stack.append((ny, nx))
                comps.append(comp)
    return comps


def test_label_components_matches_flood_fill():
    gen = torch.Generator().manual_seed(0)
    for density in (0.2, 0.45, 0.6):
        mask = torch.rand(1, 21, 33, generator=gen) < density
        labels = label_components(mask)[0]
        comps = _flood_components(mask[0])
        got = {}
        for y, x in zip(*torch.nonzero(labels >= 0, as_tuple=True)):
            got.setdefault(int(labels[y, x]), set()).add((int(y), int(x)))
        assert sorted(map(sorted, got.values())) == sorted(map(sorted, comps))


def test_connected_groups_stats_and_snake():
    # a long snake is one group; its box and magnitude sum are exact
    e = torch.zeros(1, 9, 12)
    e[0, 1, 1:11] = 0.5
    e[0, 1:8, 10] = 0.5
    e[0, 7, 2:11] = 0.5
    e[0, 4, 4] = 1.0  # an isolated pixel is its own group
    g = connected_groups(e, None)
    assert len(g) == 2
    order = torch.argsort(g.magnitude)
    assert g.magnitude[order].tolist() == [1.0, 0.5 * float((e[0] == 0.5).sum())]
    big = order[1]
    assert (g.x1[big], g.y1[big], g.x2[big], g.y2[big]) == (1, 1, 10, 7)
    assert g.batch.tolist() == [0, 0]


def test_connected_groups_cut_at_tiles():
    e = torch.zeros(2, 8, 16)
    e[1, 3, :] = 1.0  # one row across two 8-px tiles: two groups in image 1
    g = connected_groups(e, 8)
    assert len(g) == 2 and g.batch.tolist() == [1, 1]
    assert sorted(zip(g.x1.tolist(), g.x2.tolist())) == [(0, 7), (8, 15)]
    assert g.magnitude.dtype == torch.float64 and g.magnitude.tolist() == [8.0, 8.0]


def _tensor_path(edges: torch.Tensor, cell: int | None):
    from reeb_torch.stages.groups import _coords, _stats

    b, h, w = edges.shape
    xs, ys = _coords(b, h, w, edges.device)
    labels = label_components(edges > 0, cell).view(-1)
    return _stats(labels, edges.reshape(-1), xs.reshape(-1), ys.reshape(-1), h * w)


def test_compiled_groups_equal_the_tensor_path(sample_image):
    # the CPU union-find gives the FastSV tensor path's groups: same order, same bounds,
    # same float64 masses, on random masks and on the sample's edge map, tiles or not
    from reeb_torch.stages import edges as E

    gen = torch.Generator().manual_seed(3)
    cases = [torch.rand(3, 29, 47, generator=gen) * (torch.rand(3, 29, 47, generator=gen) < d)
             for d in (0.1, 0.4, 0.7)]
    cases.append(E.edge_map(E.to_gray(sample_image[None, :, :160, :480].float() / 255), 1.0, 0.05, True, True))
    nan = cases[0].clone()
    nan[0, 3, 4] = float("nan")  # NaN is background, as edges > 0 says
    cases.append(nan)
    for e in cases:
        for cell in (None, 8, 3):
            got, ref = connected_groups(e, cell), _tensor_path(e, cell)
            assert len(got) == len(ref) > 0
            for f in ("batch", "x1", "y1", "x2", "y2", "magnitude"):
                assert torch.equal(getattr(got, f), getattr(ref, f)), (f, cell)
