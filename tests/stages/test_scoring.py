"""Eq. 1 scoring against brute-force loops on random small inputs."""

from __future__ import annotations

import pytest
import torch

from reeb_torch.stages.groups import EdgeGroups
from reeb_torch.stages.scoring import box_sums, centre_box, combined_score, edge_score, enclosed_sums, integral_image
from reeb_torch.stages.windows import WindowSize


def _random_groups(b: int, h: int, w: int, n: int, gen: torch.Generator) -> EdgeGroups:
    x1 = torch.randint(0, w, (n,), generator=gen)
    y1 = torch.randint(0, h, (n,), generator=gen)
    x2 = torch.minimum(x1 + torch.randint(0, 6, (n,), generator=gen), torch.tensor(w - 1))
    y2 = torch.minimum(y1 + torch.randint(0, 6, (n,), generator=gen), torch.tensor(h - 1))
    return EdgeGroups(batch=torch.randint(0, b, (n,), generator=gen), x1=x1, y1=y1, x2=x2, y2=y2,
                      magnitude=torch.rand(n, generator=gen) + 0.1)


def _brute_enclosed(g: EdgeGroups, b: int, s: WindowSize) -> torch.Tensor:
    out = torch.zeros(b, s.ny, s.nx, dtype=torch.float64)
    for j in range(s.ny):
        for i in range(s.nx):
            x0, y0 = i * s.sx, s.oy + j * s.sy
            for k in range(len(g)):
                if (x0 <= g.x1[k] and g.x2[k] <= x0 + s.w - 1 and y0 <= g.y1[k] and g.y2[k] <= y0 + s.h - 1):
                    out[g.batch[k], j, i] += float(g.magnitude[k])
    return out


def test_enclosed_sums_match_brute_force():
    gen = torch.Generator().manual_seed(0)
    for trial in range(4):
        b, h, w = 2, 17 + trial, 23 + 2 * trial
        g = _random_groups(b, h, w, 40, gen)
        sizes = []
        for ww, hh, sx, sy in [(5, 5, 1, 1), (8, 6, 2, 3), (11, 9, 3, 2), (w, h, 1, 1), (7, 12, 4, 1)]:
            sizes.append(WindowSize(ww, hh, sx, sy, (w - ww) // sx + 1, (h - hh) // sy + 1))
        # a size whose rows start below the top (the ground band) and stop early
        sizes.append(WindowSize(6, 5, 2, 2, (w - 6) // 2 + 1, 3, oy=4))
        got = enclosed_sums(g, b, sizes)
        for s, e in zip(sizes, got):
            torch.testing.assert_close(e.double(), _brute_enclosed(g, b, s), rtol=1e-5, atol=1e-4)


def test_enclosed_sums_without_groups_are_zero():
    empty = EdgeGroups(*(torch.zeros(0, dtype=torch.long) for _ in range(5)), magnitude=torch.zeros(0))
    s = WindowSize(4, 4, 1, 1, 3, 2)
    (e,) = enclosed_sums(empty, 2, [s])
    assert e.shape == (2, 2, 3) and bool((e == 0).all())


def test_box_sums_match_direct_sums():
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(2, 13, 19, generator=gen)
    ii = integral_image(x)
    s = WindowSize(6, 4, 2, 3, (19 - 6) // 2 + 1, (13 - 4 - 2) // 3 + 1, oy=2)
    dx, dy, cw, ch = centre_box(s.w, s.h, 0.5)
    got = box_sums(ii, dx, dy, cw, ch, s)
    for j in range(s.ny):
        for i in range(s.nx):
            x0, y0 = i * s.sx + dx, s.oy + j * s.sy + dy
            ref = x[:, y0: y0 + ch, x0: x0 + cw].double().sum((1, 2))
            torch.testing.assert_close(got[:, j, i], ref, rtol=1e-5, atol=1e-5)


def test_centre_box_is_half_the_window_and_centred():
    assert centre_box(20, 10, 0.5) == (5, 2, 10, 5)
    assert centre_box(7, 7, 0.5) == (1, 1, 4, 4) or centre_box(7, 7, 0.5) == (2, 2, 4, 4)


def test_edge_score_hand_worked():
    enc, ctr = torch.tensor([10.0]), torch.tensor([2.0])
    # perimeter: (2 (w + h))^1.5 = 40^1.5
    torch.testing.assert_close(edge_score(enc, ctr, 12.0, 8.0, "perimeter", 1.5, 0.75), torch.tensor([8.0 / 40.0**1.5]))
    # area: 2 * (w h)^γ
    torch.testing.assert_close(edge_score(enc, ctr, 12.0, 8.0, "area", 1.5, 0.5), torch.tensor([8.0 / (2 * 96.0**0.5)]))


def test_combined_score_eq12():
    s, loc, road = torch.tensor([2.0]), torch.tensor([0.5]), torch.tensor([0.25])
    torch.testing.assert_close(combined_score(s, loc, road, 0.6, 0.4, "reward"), torch.tensor([2 * (0.3 + 0.1)]))
    torch.testing.assert_close(combined_score(s, loc, road, 0.6, 0.4, "none"), torch.tensor([2 * 0.3]))


def test_shadow_strips_and_fraction_on_a_synthetic_road():
    from reeb_torch.stages.scoring import apply_shadow, shadow_fraction, shadow_strips

    # a 20 x 20 box over a grey road (0.5) whose bottom 4 rows are dark (0.1) between its wheels
    sh, mx = shadow_strips(20, 20, 0.2, 0.15)
    assert (sh, mx) == (4, 3)
    assert shadow_strips(3, 2, 0.01, 0.49) == (1, 1)  # at least one row, at least one column
    grey = torch.full((1, 60, 40), 0.5)
    grey[0, 30:34, 10:30] = 0.1  # the box is x in [10, 30), y in [14, 34)
    ii = integral_image(grey)
    s = WindowSize(20, 20, 1, 1, 1, 1, oy=14)
    crop = ii[:, :, 10:]  # the box starts at column 0 of the crop
    cols = s.w - 2 * mx
    inside = box_sums(crop - crop[:, :, :1], mx, s.h - sh, cols, sh, s)
    below = box_sums(crop - crop[:, :, :1], mx, s.h, cols, sh, s)
    u = shadow_fraction(inside, below, sh * cols, torch.tensor([[[sh * cols]]]))
    torch.testing.assert_close(u, torch.tensor([[[0.8]]], dtype=torch.float64))
    # no pixel below the box (it ends at the image bottom): U = 0; lighter inside: U = 0
    assert float(shadow_fraction(inside, below, sh * cols, torch.tensor([[[0]]]))) == 0.0
    assert float(shadow_fraction(below, inside, sh * cols, torch.tensor([[[sh * cols]]]))) == 0.0
    # the factor: (floor + U)^p on finite scores; -inf stays -inf
    v = torch.tensor([2.0, -float("inf")])
    out = apply_shadow(v, torch.tensor([0.8, 0.5], dtype=torch.float64), 0.2, 0.5)
    assert out.dtype == torch.float32 and out[0] == 2.0 and out[1] == -float("inf")


def test_shadow_fraction_is_a_fraction():
    from reeb_torch.stages.scoring import shadow_fraction

    gen = torch.Generator().manual_seed(7)
    n = torch.randint(1, 50, (500,), generator=gen)
    rows = torch.randint(0, 50, (500,), generator=gen)
    u = shadow_fraction(torch.rand(500, generator=gen, dtype=torch.float64) * n,
                        torch.rand(500, generator=gen, dtype=torch.float64) * rows, n.double(), rows)
    assert bool(((u >= 0) & (u <= 1)).all()) and bool((u[rows == 0] == 0).all())


def test_select_per_region_cpu_matches_a_stable_sort_with_ties():
    import numpy as np

    from reeb_torch.stages.scoring import select_per_region_cpu

    gen = torch.Generator().manual_seed(11)
    b, n = 3, 400
    scores = torch.rand(b, n, generator=gen)
    scores[:, ::3] = 0.0  # windows without edges: many ties, also at the cut
    scores[:, 1::7] = -float("inf")  # dropped windows never count
    regions = [torch.arange(0, 250), torch.arange(200, 400), torch.arange(0, 400, 5)]  # overlapping
    members = np.concatenate([r.numpy() for r in regions]).astype(np.int64)
    starts = np.cumsum([0] + [len(r) for r in regions]).astype(np.int64)
    budget = torch.tensor([[10, 180, 0], [240, 5, 60], [1, 1, 500]])
    got = select_per_region_cpu(scores, members, starts, budget)
    want = torch.zeros(b, n, dtype=torch.bool)
    for i in range(b):
        for r, idx in enumerate(regions):
            vals, pos = scores[i, idx].sort(descending=True, stable=True)
            take = pos[: int(budget[i, r])][torch.isfinite(vals[: int(budget[i, r])])]
            want[i, idx[take]] = True
    assert torch.equal(got, want)


def test_compiled_integral_image_equals_the_cumulative_sums():
    # the CPU pass sums in the tensor ops' order (rows, then columns): equal bit for bit,
    # in its blocks of four rows and in the rows left over (heights 23 and 3)
    gen = torch.Generator().manual_seed(4)
    for x in (torch.rand(3, 20, 31, generator=gen) ** 8, torch.rand(2, 23, 17, generator=gen) ** 8,
              torch.rand(1, 3, 5, generator=gen), torch.rand(1, 1, 1, generator=gen), torch.zeros(2, 4, 0)):
        ref = torch.zeros(x.shape[0], x.shape[1] + 1, x.shape[2] + 1, dtype=torch.float64)
        ref[:, 1:, 1:] = x.double().cumsum(2).cumsum(1)
        assert torch.equal(integral_image(x), ref)


def test_vegetation_factor_is_one_minus_the_green_share_to_the_power():
    from reeb_torch.stages.scoring import vegetation_factor

    sums = torch.tensor([0.0, 50.0, 100.0], dtype=torch.float64)
    assert vegetation_factor(sums, 100.0, 3).tolist() == [1.0, 0.125, 0.0]
    assert vegetation_factor(sums, 100.0, 1).tolist() == [1.0, 0.5, 0.0]


def test_count_integral_equals_the_float_integral_image():
    from reeb_torch.stages.scoring import count_integral

    gen = torch.Generator().manual_seed(5)
    for m in ((torch.rand(3, 17, 29, generator=gen) > 0.6).float(), torch.zeros(2, 1, 1), torch.ones(1, 4, 6)):
        got = count_integral(m)
        assert got.dtype == torch.int32 and torch.equal(got.double(), integral_image(m))


def test_kth_largest_radix_selection_equals_a_sort():
    import numpy as np

    from reeb_torch.stages._radix import kth_largest

    rng = np.random.default_rng(0)
    for t in range(200):
        n = int(rng.integers(1, 2000))
        v = rng.standard_normal(n).astype(np.float32)
        if t % 3 == 0:
            v = np.round(v, 1).astype(np.float32)  # ties
        if t % 5 == 0:
            v[rng.integers(0, n, n // 4)] = -np.inf
        if t % 7 == 0:
            v[rng.integers(0, n, n // 5)] = -0.0
        if t % 11 == 0:
            v[rng.integers(0, n, n // 6)] = np.nan
        k = int(rng.integers(1, n + 1))
        ref = -np.sort(-np.where(np.isnan(v), -np.inf, v))[k - 1]
        assert kth_largest(v, k) == ref, t


def test_location_shape_fit_by_hand():
    """The class fit reads the box's shape: a class's height fit times a soft interval on
    the box's width on the road, worked by hand for a camera 1.5 m up, horizon at row 100 of a 300-row image."""
    import math

    from reeb_torch.stages.scoring import class_width_fits, location_score

    bottom = torch.tensor([250.0, 250.0, 250.0, 90.0], dtype=torch.float64)  # 150 px below the horizon; one above
    bh = torch.tensor([150.0, 150.0, 150.0, 20.0], dtype=torch.float64)      # 1.5 m tall at that depth
    bw = torch.tensor([40.0, 200.0, 1000.0, 20.0], dtype=torch.float64)      # 0.4 m, 2 m, 10 m wide
    ratios, weights = (1.0, 1.2), (1.0, 0.5)  # a 1.5 m class and a 1.8 m one (weight 0.5)
    widths = ((1.3, 6.5), (0.3, 1.4))         # car-like and person-like width ranges
    sigma = 0.3
    got = location_score(bottom, bw, bh, 640.0, 300.0, "classes", 1 / 3, ratios, sigma, weights, widths, 1.5)

    def gauss(d):
        return math.exp(-d * d / (2 * sigma * sigma))

    h_fit = [1.0, 0.5 * gauss(math.log(1.0 / 1.2))]  # class 0 fits the height exactly
    metres = [0.4, 2.0, 10.0]
    for i, wm in enumerate(metres):
        w_fit = [gauss(max(math.log(lo) - math.log(wm), 0) + max(math.log(wm) - math.log(hi), 0))
                 for lo, hi in widths]
        assert float(got[i]) == pytest.approx(max(h * w for h, w in zip(h_fit, w_fit)), rel=1e-12)
    assert float(got[1]) == pytest.approx(1.0)          # 2 m wide, 1.5 m tall: the car-like class, fully
    assert float(got[0]) < 0.5                          # person-shaped: no longer the car class's fit
    assert float(got[3]) == 0.0                         # above the horizon
    plain = location_score(bottom, bw, bh, 640.0, 300.0, "classes", 1 / 3, ratios, sigma, weights)
    assert float(plain[0]) == pytest.approx(1.0)        # the height fit alone takes the car class's fit
    inside = class_width_fits(bottom[:2], bw[:2], 300.0, 1 / 3, ((0.2, 3.0),), sigma, 1.5)[0]
    assert torch.equal(inside, torch.ones(2, dtype=torch.float64))  # inside the range: 1 exactly


def test_row_order_takes_every_window_row_once_by_bottom_row():
    import numpy as np

    from reeb_torch.stages.scoring import PLAN_COLUMNS, row_order

    gen = np.random.default_rng(0)
    plan = np.zeros((7, len(PLAN_COLUMNS)), np.int64)
    col = {c: i for i, c in enumerate(PLAN_COLUMNS)}
    plan[:, col["h"]] = gen.integers(3, 40, 7)
    plan[:, col["sy"]] = gen.integers(1, 5, 7)
    plan[:, col["ny"]] = [4, 0, 1, 9, 3, 3, 6]  # a size without rows too
    plan[:, col["oy"]] = gen.integers(0, 8, 7)
    order = row_order(plan)
    assert order.dtype == np.int64 and order.flags.c_contiguous
    rows = [(k, j) for k in range(7) for j in range(plan[k, col["ny"]])]
    assert sorted(map(tuple, order.tolist())) == rows
    bottom = [plan[k, col["oy"]] + j * plan[k, col["sy"]] + plan[k, col["h"]] for k, j in order.tolist()]
    assert all((b0, k0) <= (b1, k1) for b0, b1, (k0, _), (k1, _) in zip(bottom, bottom[1:], order, order[1:]))
