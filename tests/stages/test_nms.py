"""nms_top_k equals torchvision's NMS truncated to k."""

from __future__ import annotations

import torch
from torchvision.ops import nms

from reeb_torch.stages.nms import nms_top_k


def _boxes(n: int, gen: torch.Generator) -> torch.Tensor:
    xy = torch.rand(n, 2, generator=gen) * 200
    wh = torch.rand(n, 2, generator=gen) * 60 + 5
    return torch.cat([xy, xy + wh], 1)


def test_matches_torchvision_for_many_k():
    gen = torch.Generator().manual_seed(0)
    for n in (1, 50, 3000):
        b = _boxes(n, gen)
        s = torch.rand(n, generator=gen)
        ref = nms(b, s, 0.7)
        for k in (1, 10, 200, 5000):
            got = nms_top_k(b, s, 0.7, k, first=min(k, 16))
            assert torch.equal(got, ref[:k])


def test_ties_keep_input_order_and_empty_input():
    b = torch.tensor([[0.0, 0, 10, 10], [0, 0, 10, 10], [50, 50, 60, 60]])
    s = torch.tensor([1.0, 1.0, 1.0])
    assert nms_top_k(b, s, 0.5, 5).tolist() == [0, 2]
    assert nms_top_k(torch.zeros(0, 4), torch.zeros(0), 0.5, 5).numel() == 0


# -- the compiled grid-bucketed CPU path (reeb_torch.stages.nms._grid_nms_sorted) ----------------
import pytest  # noqa: E402

from reeb_torch.stages.nms import _grid_ok  # noqa: E402

THRESHOLDS = (0.5, 0.55, 0.6, 0.7, 0.8, 0.9, 0.95)


def _messy_boxes(n: int, gen: torch.Generator, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Boxes on an integer lattice (exact duplicates, shared edges), zero-width/height ones,
    and scores with many ties."""
    xy = torch.randint(0, 80, (n, 2), generator=gen).to(dtype)
    wh = torch.randint(0, 40, (n, 2), generator=gen).to(dtype)
    wh[torch.rand(n, generator=gen) < 0.05] = 0  # degenerate points
    b = torch.cat([xy, xy + wh], 1)
    dup = torch.randint(0, n, (n // 4,), generator=gen)
    b[torch.randint(0, n, (n // 4,), generator=gen)] = b[dup]  # identical boxes
    s = torch.randint(0, 6, (n,), generator=gen).to(dtype)  # ties
    return b, s


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grid_path_equals_torchvision_on_random_boxes_with_ties(dtype):
    gen = torch.Generator().manual_seed(1)
    for seed in range(60):
        n = int(torch.randint(1, 600, (1,), generator=gen))
        if seed % 2:
            b, s = _messy_boxes(n, gen, dtype)
        else:
            b, s = _boxes(n, gen).to(dtype), torch.rand(n, generator=gen).to(dtype)
        assert _grid_ok(b, 0.5)
        for thr in THRESHOLDS:
            ref = nms(b, s, thr)
            assert torch.equal(nms_top_k(b, s, thr, n), ref), (seed, thr)
            assert torch.equal(nms_top_k(b, s, thr, 7), ref[:7]), (seed, thr)


def test_grid_path_at_iou_just_above_half_on_shifted_copies():
    # pairs whose IoU sits at and around 0.5, where centre containment is tight
    base = torch.tensor([[0.0, 0, 10, 10]])
    shifts = torch.linspace(0, 6, 241)
    b = torch.cat([base.expand(len(shifts), 4) + torch.stack([shifts, 0 * shifts, shifts, 0 * shifts], 1),
                   base * 3 + 100], 0)
    s = torch.ones(len(b))
    for thr in (0.5, 0.5 + 1e-7, 0.6):
        assert torch.equal(nms_top_k(b, s, thr, len(b)), nms(b, s, thr))


def test_fallback_below_half_and_on_invalid_boxes():
    gen = torch.Generator().manual_seed(2)
    b, s = _messy_boxes(300, gen, torch.float32)
    for thr in (0.0, 0.1, 0.3, 0.49):
        assert not _grid_ok(b, thr)
        assert torch.equal(nms_top_k(b, s, thr, 300), nms(b, s, thr))
    flipped = b.clone()
    flipped[0] = torch.tensor([10.0, 10, 0, 0])  # x2 < x1: torchvision's path
    assert not _grid_ok(flipped, 0.7)
    assert torch.equal(nms_top_k(flipped, s, 0.7, 300), nms(flipped, s, 0.7))
    assert not _grid_ok(b.half(), 0.7)


def test_top_k_early_stop_equals_truncation():
    gen = torch.Generator().manual_seed(3)
    b, s = _boxes(4000, gen), torch.rand(4000, generator=gen)
    ref = nms(b, s, 0.7)
    for k in (0, 1, 2, 50, len(ref) - 1, len(ref), len(ref) + 1, 10**6):
        assert torch.equal(nms_top_k(b, s, 0.7, k), ref[:k]), k


def test_empty_input_on_both_paths():
    for thr in (0.3, 0.7):
        out = nms_top_k(torch.zeros(0, 4), torch.zeros(0), thr, 5)
        assert out.dtype == torch.long and out.numel() == 0


def test_generator_candidates_equal_torchvision():
    """Real candidates: the boxes the generator hands to NMS on a bundled KITTI frame."""
    from pathlib import Path

    import reeb_torch.selection.suppress as R
    from reeb_torch import ProposalGenerator, get_preset
    from reeb_torch.io import read_image

    path = Path(__file__).resolve().parents[2] / "examples" / "data" / "kitti_000001.png"
    caught = []

    def spy(chosen, boxes, scores, iou, k, boxes_ok=None, classes=None, need=None, thin=(0.0, 0.0)):
        assert classes is None and need is None and thin[0] <= iou  # no quota, one threshold here
        for i in range(chosen.shape[0]):
            cand = chosen[i].nonzero().squeeze(1)
            caught.append((boxes[cand], scores[i, cand], iou, k))
        return orig(chosen, boxes, scores, iou, k, boxes_ok)

    gen = ProposalGenerator(get_preset("training-free").replace(use_regions=False))
    gen([read_image(path)])  # a first call warms the kernels up on a picture of its own, not to be caught
    orig, R.nms_windows_cpu = R.nms_windows_cpu, spy
    try:
        out = gen([read_image(path)])
    finally:
        R.nms_windows_cpu = orig
    assert caught
    for boxes, scores, iou, k in caught:
        assert boxes.shape[0] > k and _grid_ok(boxes, iou)
        ref = nms(boxes, scores, iou)[:k]
        assert torch.equal(nms_top_k(boxes, scores, iou, k), ref)
        assert torch.equal(out[0]["boxes"], boxes[ref])


try:
    from hypothesis import given, settings
    from hypothesis import strategies as st
except ImportError:  # hypothesis is in the dev extra
    pass
else:

    @settings(max_examples=150, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 30), st.integers(0, 12), st.integers(0, 12),
                              st.integers(0, 3)), min_size=1, max_size=60),
           st.sampled_from(THRESHOLDS), st.integers(1, 70))
    def test_hypothesis_equals_torchvision(rows, thr, k):
        t = torch.tensor(rows, dtype=torch.float32)
        b = torch.cat([t[:, :2], t[:, :2] + t[:, 2:4]], 1) / 4  # quarter-pixel lattice
        s = t[:, 4]
        assert torch.equal(nms_top_k(b, s, thr, k), nms(b, s, thr)[:k])


def test_nms_top_k_many_equals_one_image_at_a_time():
    from reeb_torch.stages.nms import nms_top_k, nms_top_k_many

    gen = torch.Generator().manual_seed(9)
    pairs = []
    for n in (300, 0, 57, 1000, 1):
        xy = torch.rand(n, 2, generator=gen) * 200
        wh = torch.rand(n, 2, generator=gen) * 60 + 1
        pairs.append((torch.cat([xy, xy + wh], 1), torch.rand(n, generator=gen).round(decimals=1)))  # ties
    for iou, k in ((0.7, 50), (0.5, 1000), (0.3, 20)):  # 0.3: the torchvision path
        got = nms_top_k_many(pairs, iou, k)
        for (b, s), g in zip(pairs, got):
            assert torch.equal(g, nms_top_k(b, s, iou, k))


def test_nms_windows_cpu_equals_nms_top_k_on_the_chosen_windows():
    # gathering, radix sort and NMS compiled per image give nms_top_k's windows,
    # ties (and -0.0 against 0.0) included; NaN scores and bad boxes take the checked path
    from reeb_torch.stages.nms import nms_windows_cpu

    gen = torch.Generator().manual_seed(11)
    b, s = _messy_boxes(3000, gen, torch.float32)
    scores = torch.stack([s, -s, torch.rand(3000, generator=gen), s * 0, (s - 3).clamp(max=0) * 0.5])
    scores[3, ::3] = -0.0
    scores[4, :5] = float("nan")
    chosen = torch.rand(5, 3000, generator=gen) < 0.6
    chosen[2] = False  # an image without candidates
    bad = b.clone()
    bad[chosen[1].nonzero()[0, 0]] = torch.tensor([5.0, 5.0, 1.0, 9.0])  # x2 < x1
    for boxes in (b, bad):
        for iou, k in ((0.5, 3000), (0.7, 100), (0.95, 1)):
            got = nms_windows_cpu(chosen, boxes, scores, iou, k)
            for i in range(5):
                cand = chosen[i].nonzero().squeeze(1)
                assert torch.equal(got[i], cand[nms_top_k(boxes[cand], scores[i, cand], iou, k)]), (i, iou, k)
    assert nms_windows_cpu(chosen, b, scores, 0.3, 10) is None  # the torchvision path
    assert nms_windows_cpu(chosen, b.double(), scores, 0.7, 10) is None


def test_nms_windows_cpu_with_class_needs_stops_where_the_quota_is_decided():
    """With an output quota per class (or region) the NMS goes past k only until each has its need
    among the kept boxes: the quota's output is that of the NMS run to the end (NaN and bad
    boxes, the checked path, included), and it stops early where the needs fill."""
    from reeb_torch import ReebConfig
    from reeb_torch.selection import Suppression
    from reeb_torch.stages.nms import nms_windows_cpu

    gen = torch.Generator().manual_seed(5)
    b, s = _messy_boxes(3000, gen, torch.float32)
    scores = torch.stack([s, -s, torch.rand(3000, generator=gen), s.clone()])
    scores[3, :5] = float("nan")
    chosen = torch.rand(4, 3000, generator=gen) < 0.6
    classes = torch.multinomial(torch.tensor([0.8, 0.12, 0.06, 0.02]), 4 * 3000, True, generator=gen).view(4, 3000)
    for k, share in ((100, [0.0, 0.3, 0.1, 0.05]), (100, [0.0, 0.0, 0.0, 0.0]), (40, [0.0, 0.2, 0.05, 0.9 / 40])):
        rk = Suppression(ReebConfig(top_k=k).nms)
        share = torch.tensor(share)
        need = rk.quota_counts(share)
        for boxes in (b, b.clone().index_put_((chosen[1].nonzero()[0, 0],), torch.tensor([5.0, 5.0, 1.0, 9.0]))):
            short = nms_windows_cpu(chosen, boxes, scores, 0.7, k, None, classes, need)
            full = nms_windows_cpu(chosen, boxes, scores, 0.7, 3000)
            for i in range(4):
                assert torch.equal(full[i][: len(short[i])], short[i])  # a prefix of the whole NMS
                assert torch.equal(rk.quota(short[i], classes[i, short[i]], share, whole=True)[:k],
                                   rk.quota(full[i], classes[i, full[i]], share, whole=True)[:k]), (k, i)
            if boxes is b and not bool(need.any()):  # no quota: k, as without classes (NaN: the checked path)
                assert len(short[0]) == len(short[1]) == len(short[2]) == k
    # needs per image (each image's groups by its own shares)
    rk = Suppression(ReebConfig(top_k=100).nms)
    shares = torch.tensor([[0.5, 0.3, 0.2, 0.0], [0.1, 0.1, 0.1, 0.7], [0.0, 0.0, 0.0, 1.0], [0.25, 0.25, 0.25, 0.25]])
    need = torch.stack([rk.quota_counts(sh, float(sh.sum())) for sh in shares])
    short = nms_windows_cpu(chosen, b, scores, 0.7, 100, None, classes, need)
    full = nms_windows_cpu(chosen, b, scores, 0.7, 3000)
    for i in range(4):
        assert torch.equal(full[i][: len(short[i])], short[i])
        assert torch.equal(rk.quota(short[i], classes[i, short[i]], shares[i])[:100],
                           rk.quota(full[i], classes[i, full[i]], shares[i])[:100]), i
    # where every need fills early, far fewer boxes than the whole NMS
    few = nms_windows_cpu(chosen, b, scores, 0.7, 100, None, classes, torch.tensor([0, 5, 2, 1]))
    assert all(100 <= len(x) < 200 for x in few[:3])


def test_descending_radix_order_equals_torch_stable_sort():
    from reeb_torch.stages._radix import descending_order

    gen = torch.Generator().manual_seed(12)
    for n in (0, 1, 5, 4097):
        v = torch.randn(n, generator=gen)
        if n > 4:
            v[torch.randint(0, n, (n // 3,), generator=gen)] = 0.5  # ties
            v[torch.randint(0, n, (n // 5,), generator=gen)] = -0.0
            v[torch.randint(0, n, (n // 5,), generator=gen)] = 0.0
            v[:2] = torch.tensor([float("inf"), float("-inf")])
        ref = torch.sort(v, descending=True, stable=True).indices
        assert torch.equal(torch.from_numpy(descending_order(v.numpy())), ref), n


def test_nms_windows_cpu_sorts_a_prefix_first_and_all_when_it_keeps_too_few():
    # only the best 3k candidates are sorted first; when they hold fewer than k
    # distinct boxes (here the best 40 are one box) it falls back to all: same windows
    from reeb_torch.stages.nms import nms_windows_cpu

    gen = torch.Generator().manual_seed(5)
    n = 600
    xy = torch.rand(n, 2, generator=gen) * 500
    boxes = torch.cat([xy, xy + torch.rand(n, 2, generator=gen) * 80 + 5], 1)
    boxes[:40] = torch.tensor([10.0, 10.0, 60.0, 60.0])
    scores = torch.rand(2, n, generator=gen)
    scores[:, :40] += 2.0  # the duplicates rank first
    scores[1, 100:300] = 0.5  # ties across the prefix's cut
    chosen = torch.ones(2, n, dtype=torch.bool)
    for k in (5, 12, 30, 200):
        got = nms_windows_cpu(chosen, boxes, scores, 0.7, k)
        for i in range(2):
            assert torch.equal(got[i], nms_top_k(boxes, scores[i], 0.7, k)), (i, k)


def _greedy_by_hand(b: torch.Tensor, s: torch.Tensor, iou: float, thin: tuple[float, float], k: int) -> list[int]:
    """Greedy NMS written out: a thin box's threshold is ``thin[0]``."""
    from torchvision.ops import box_iou

    kept: list[int] = []
    for i in torch.sort(s, descending=True, stable=True).indices.tolist():
        w, h = float(b[i, 2] - b[i, 0]), float(b[i, 3] - b[i, 1])
        t = max(thin[0], iou) if w < thin[1] * h else iou
        if not kept or not bool((box_iou(b[i: i + 1], b[kept])[0] > t).any()):
            kept.append(i)
        if len(kept) == k:
            break
    return kept


def test_thin_boxes_are_suppressed_only_above_their_own_threshold():
    """nms_top_k's ``thin``: every path (the compiled grid kernel, the window kernel, the
    tensor loop of other devices) keeps what greedy NMS with a threshold of its own for the
    thin boxes keeps; a thin box's tight and loose copies both survive at 0.75."""
    from reeb_torch.stages.nms import _greedy_thin, nms_windows_cpu

    tall = torch.tensor([[0.0, 0, 20, 60], [0, 0, 24, 60], [100, 0, 160, 40], [100, 0, 166, 40]])
    s = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert nms_top_k(tall, s, 0.75, 10).tolist() == [3, 1]  # IoU 20/24 = 0.83 and 60/66 = 0.91
    assert nms_top_k(tall, s, 0.75, 10, thin=(0.85, 0.5)).tolist() == [3, 1, 0]  # 20 < 0.5 · 60
    gen = torch.Generator().manual_seed(3)
    for n in (50, 800):
        xy = torch.rand(n, 2, generator=gen) * 100
        wh = torch.rand(n, 2, generator=gen) * torch.tensor([20.0, 60.0]) + 4
        b = torch.cat([xy, xy + wh], 1)
        sc = torch.rand(n, generator=gen)
        for thin in ((0.8, 0.5), (0.9, 0.4)):
            want = _greedy_by_hand(b, sc, 0.75, thin, 60)
            assert nms_top_k(b, sc, 0.75, 60, thin=thin).tolist() == want
            order = torch.sort(sc, descending=True, stable=True).indices
            assert order[_greedy_thin(b[order], 0.75, thin, 60)].tolist() == want
            got = nms_windows_cpu(torch.ones(1, n, dtype=torch.bool), b, sc[None], 0.75, 60, thin=thin)[0]
            assert got.tolist() == want
