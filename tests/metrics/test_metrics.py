"""Tests of reeb_torch.metrics.recall against hand-worked cases and a brute-force loop."""

from __future__ import annotations

import json
import math

import pytest
import torch

from reeb_torch.metrics.recall import (
    AR_IOUS,
    KITTI_DIFFICULTIES,
    KittiDifficulty,
    average_recall,
    best_iou,
    bootstrap_recalls,
    compare_recall,
    kitti_difficulty_mask,
    object_hits,
    recall_interval,
    recall_table,
    recall_vs_iou,
    recall_vs_proposals,
    select_objects,
    sign_test,
)

T = torch.tensor

# Two GT boxes of area 100; each proposal overlaps one of them with a known IoU.
GT = T([[0.0, 0.0, 10.0, 10.0], [100.0, 100.0, 110.0, 110.0]])
PROPS = T(
    [
        [0.0, 0.0, 10.0, 4.0],  # IoU 0.4 with GT 0
        [100.0, 100.0, 110.0, 108.0],  # IoU 0.8 with GT 1
        [0.0, 0.0, 10.0, 6.0],  # IoU 0.6 with GT 0
        [0.0, 0.0, 10.0, 9.0],  # IoU 0.9 with GT 0
    ]
)
# best IoU of (GT 0, GT 1) with the top k, k = 1..4
HAND_BEST = {1: (0.4, 0.0), 2: (0.4, 0.8), 3: (0.6, 0.8), 4: (0.9, 0.8)}


def brute_best_iou(props: torch.Tensor, gt: torch.Tensor, k: int) -> list[float]:
    """Best IoU per GT box with the top k proposals, by plain Python loops."""
    out = []
    for g in gt.tolist():
        best = 0.0
        for p in props[:k].tolist():
            iw = max(0.0, min(g[2], p[2]) - max(g[0], p[0]))
            ih = max(0.0, min(g[3], p[3]) - max(g[1], p[1]))
            inter = iw * ih
            union = (g[2] - g[0]) * (g[3] - g[1]) + (p[2] - p[0]) * (p[3] - p[1]) - inter
            best = max(best, inter / union if union > 0 else 0.0)
        out.append(best)
    return out


def test_best_iou_hand_case():
    for k, expected in HAND_BEST.items():
        torch.testing.assert_close(best_iou(PROPS, GT, top_k=k), T(expected))
    torch.testing.assert_close(best_iou(PROPS, GT), T([0.9, 0.8]))  # all proposals
    torch.testing.assert_close(best_iou(PROPS, GT, top_k=100), T([0.9, 0.8]))
    assert best_iou(PROPS, GT, top_k=0).tolist() == [0.0, 0.0]
    assert best_iou(torch.zeros(0, 4), GT).tolist() == [0.0, 0.0]
    assert best_iou(PROPS, torch.zeros(0, 4)).shape == (0,)
    assert best_iou({"boxes": PROPS, "scores": torch.ones(4)}, GT, top_k=2).tolist() == [
        pytest.approx(0.4),
        pytest.approx(0.8),
    ]


def test_best_iou_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(300, 2, generator=g) * 200
    props = torch.cat([xy, xy + 5 + torch.rand(300, 2, generator=g) * 60], dim=1)
    xy = torch.rand(7, 2, generator=g) * 200
    gt = torch.cat([xy, xy + 5 + torch.rand(7, 2, generator=g) * 60], dim=1)
    for k in (1, 10, 77, 300):
        torch.testing.assert_close(
            best_iou(props, gt, top_k=k), T(brute_best_iou(props, gt, k)), atol=1e-6, rtol=0
        )


def test_degenerate_boxes_give_zero_not_nan():
    point = T([[5.0, 5.0, 5.0, 5.0]])
    assert best_iou(point, point).tolist() == [0.0]


def test_recall_table_hand_case():
    ks, ious = (1, 2, 3, 4, 10), (0.3, 0.5, 0.7)
    r = recall_table([PROPS], [GT], ks=ks, ious=ious)
    expected = {  # recall = share of the 2 GT boxes with best IoU >= t
        1: (0.5, 0.0, 0.0),
        2: (1.0, 0.5, 0.5),
        3: (1.0, 1.0, 0.5),
        4: (1.0, 1.0, 1.0),
        10: (1.0, 1.0, 1.0),  # fewer proposals than k: all of them
    }
    torch.testing.assert_close(r.micro, T([expected[k] for k in ks], dtype=torch.float64))
    for k in ks:
        for t, v in zip(ious, expected[k]):
            assert r.at(k, t) == v
            # and by brute force
            assert v == sum(b >= t for b in brute_best_iou(PROPS, GT, k)) / 2
    assert r.num_objects == 2 and r.num_images == 1
    assert r.class_names == () and r.per_class.shape == (0, 5, 3)
    assert math.isnan(r.class_mean[0, 0])


def test_recall_table_matches_brute_force_several_images():
    g = torch.Generator().manual_seed(1)
    props, gts = [], []
    for n_prop, n_gt in [(50, 3), (5, 4), (0, 2), (30, 0), (120, 6)]:
        xy = torch.rand(n_prop, 2, generator=g) * 100
        props.append(torch.cat([xy, xy + 2 + torch.rand(n_prop, 2, generator=g) * 40], dim=1))
        xy = torch.rand(n_gt, 2, generator=g) * 100
        gts.append(torch.cat([xy, xy + 2 + torch.rand(n_gt, 2, generator=g) * 40], dim=1))
    ks, ious = (1, 7, 50, 100), (0.1, 0.3, 0.5, 0.7)
    r = recall_table(props, gts, ks=ks, ious=ious)
    assert r.num_images == 4 and r.num_objects == 15
    for i, k in enumerate(ks):
        best = [b for p, gt in zip(props, gts) for b in brute_best_iou(p, gt, k)]
        for j, t in enumerate(ious):
            assert r.micro[i, j].item() == pytest.approx(sum(b >= t for b in best) / 15)


def test_per_class_and_micro_differ():
    # image 0: three cars, all matched exactly; image 1: one pedestrian, missed
    cars = T([[0.0, 0.0, 10.0, 10.0], [20.0, 0.0, 30.0, 10.0], [40.0, 0.0, 50.0, 10.0]])
    ped = T([[0.0, 50.0, 5.0, 70.0]])
    props = [cars.flip(0), T([[100.0, 100.0, 120.0, 120.0]])]
    labels = [T([0, 0, 0]), T([1])]
    names = ("Car", "Pedestrian", "Cyclist")
    r = recall_table(props, [cars, ped], labels, names, ks=(1, 3), ious=(0.5,))
    assert r.at(3, 0.5) == 0.75  # 3 of 4 objects
    assert r.at(3, 0.5, "Car") == 1.0 and r.at(3, 0.5, "Pedestrian") == 0.0
    assert math.isnan(r.at(3, 0.5, "Cyclist"))  # no cyclist: left out of the mean
    assert r.at(3, 0.5, "mean") == 0.5  # (1 + 0) / 2, not / 3
    assert r.at(1, 0.5) == 0.25 and r.at(1, 0.5, "Car") == pytest.approx(1 / 3)
    assert r.num_per_class.tolist() == [3, 1, 0]

    d = json.loads(json.dumps(r.to_dict()))  # JSON-able, nan -> null
    assert d["micro"]["3"]["0.5"] == 0.75 and d["class_mean"]["3"]["0.5"] == 0.5
    assert d["per_class"]["Cyclist"]["3"]["0.5"] is None
    assert d["num_per_class"] == {"Car": 3, "Pedestrian": 1, "Cyclist": 0}

    table = r.format_table()
    lines = table.splitlines()
    assert "k=3" in table and "class mean" in table and "Car (3)" in table
    assert lines[-1].startswith("Cyclist (0)") and lines[-1].rstrip().endswith("-")
    assert "75.0" in next(ln for ln in lines if ln.startswith("all (4)"))
    assert str(r) == table


def test_empty_cases():
    # no images at all
    r = recall_table([], [], ks=(5,), ious=(0.5,))
    assert r.num_objects == 0 and math.isnan(r.micro[0, 0])
    # images without GT are skipped, images without proposals count as misses
    r = recall_table(
        [PROPS, torch.zeros(0, 4), PROPS], [torch.zeros(0, 4), GT, GT], ks=(4,), ious=(0.5,)
    )
    assert r.num_images == 2 and r.num_objects == 4 and r.at(4, 0.5) == 0.5
    # labels of images without GT may be empty
    r = recall_table(
        [PROPS, PROPS], [torch.zeros(0, 4), GT], [torch.zeros(0, dtype=torch.int64), T([0, 1])],
        ("a", "b"), ks=(2,), ious=(0.5,),
    )
    assert r.per_class[:, 0, 0].tolist() == [0.0, 1.0]


def test_input_checks():
    with pytest.raises(ValueError, match="proposal sets"):
        recall_table([PROPS], [GT, GT])
    with pytest.raises(ValueError, match=r"Tensor\[N, 4\]"):
        recall_table([PROPS[:, :3]], [GT])
    with pytest.raises(ValueError, match="labels for 2 boxes"):
        recall_table([PROPS], [GT], [T([0])], ("a",))
    with pytest.raises(ValueError, match="class indices"):
        recall_table([PROPS], [GT], [T([0, 5])], ("a", "b"))
    with pytest.raises(ValueError, match="ks"):
        recall_table([PROPS], [GT], ks=(0,))
    with pytest.raises(ValueError, match="IoU"):
        recall_table([PROPS], [GT], ious=(1.5,))


def test_average_recall_hand_case():
    # GT 0 best IoU 0.92: recalled at 0.5, 0.55, ..., 0.9 (9 of 10 thresholds)
    # GT 1 best IoU 0.72: recalled at 0.5, ..., 0.7 (5 of 10 thresholds)
    props = T([[0.0, 0.0, 10.0, 9.2], [100.0, 100.0, 110.0, 107.2]])
    assert AR_IOUS == (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)
    ar = average_recall([props], [GT], ks=(1, 2))
    torch.testing.assert_close(ar, T([0.9 / 2, (0.9 + 0.5) / 2], dtype=torch.float64))
    # per class: class 0 AR 0.9, class 1 AR 0.5 -> mean 0.7 at k = 2
    ar_c = average_recall([props], [GT], ks=(2,), gt_labels=[T([0, 1])], average="class")
    assert ar_c.item() == pytest.approx(0.7)
    with pytest.raises(ValueError, match="gt_labels"):
        average_recall([props], [GT], average="class")


def test_recall_vs_proposals():
    ks, recall = recall_vs_proposals([PROPS], [GT], iou=0.7, ks=range(1, 6))
    assert ks.tolist() == [1, 2, 3, 4, 5]
    assert recall.tolist() == [0.0, 0.5, 0.5, 1.0, 1.0]
    ks, recall = recall_vs_proposals([PROPS], [GT], iou=0.5)  # default grid up to 4
    assert ks.tolist() == [1, 2, 3, 4] and recall.tolist() == [0.0, 0.5, 1.0, 1.0]
    ks, _ = recall_vs_proposals([PROPS], [GT], max_k=2000, points=20)
    assert ks[0] == 1 and ks[-1] == 2000 and bool((ks.diff() > 0).all())


def test_recall_vs_iou():
    ious, recall = recall_vs_iou([PROPS], [GT], k=4)
    assert ious.tolist() == pytest.approx([0.5 + 0.05 * i for i in range(11)])
    # best IoUs 0.9 and 0.8 (thresholds at the exact values avoided by checking around them)
    expected = [(0.9 >= t) / 2 + (0.8 >= t) / 2 for t in ious.tolist()]
    for t, got, want in zip(ious.tolist(), recall.tolist(), expected):
        if not (math.isclose(t, 0.8) or math.isclose(t, 0.9)):
            assert got == want
    ious, recall = recall_vs_iou([PROPS], [GT], k=1, ious=torch.linspace(0, 1, 5))
    assert recall.tolist() == [1.0, 0.5, 0.0, 0.0, 0.0]  # best IoUs 0.4 and 0


# -- KITTI difficulty and per-class recall ------------------------------------------------

# (box, occluded, truncated, moderate?, easy?) worked by hand from KITTI's rules:
# moderate = height y2 - y1 >= 25, occluded <= 1, truncated <= 0.30; easy = 40, 0, 0.15.
DIFFICULTY_CASES = [
    ([0.0, 100.0, 10.0, 125.0], 1, 0.30, True, False),  # exactly on every moderate bound
    ([0.0, 100.0, 10.0, 124.9], 0, 0.00, False, False),  # 24.9 px: too small
    ([0.0, 100.0, 10.0, 140.0], 2, 0.00, False, False),  # largely occluded
    ([0.0, 100.0, 10.0, 140.0], 0, 0.31, False, False),  # truncated too much
    ([0.0, 100.0, 10.0, 150.0], 3, 0.00, False, False),  # occlusion unknown
    ([0.0, 100.0, 10.0, 140.0], 0, 0.15, True, True),  # 40 px, visible: easy too
    ([0.0, 100.0, 10.0, 139.0], 0, 0.00, True, False),  # 39 px: moderate, not easy
]


def test_kitti_difficulty_mask_hand_cases():
    boxes = T([c[0] for c in DIFFICULTY_CASES])
    occ = T([c[1] for c in DIFFICULTY_CASES])
    trunc = T([c[2] for c in DIFFICULTY_CASES], dtype=torch.float32)  # as the dataset reads it
    moderate = kitti_difficulty_mask(boxes, occ, trunc)  # default level: moderate
    assert moderate.dtype == torch.bool
    assert moderate.tolist() == [c[3] for c in DIFFICULTY_CASES]
    assert kitti_difficulty_mask(boxes, occ, trunc, "easy").tolist() == [c[4] for c in DIFFICULTY_CASES]
    # every easy object is moderate, every moderate one hard
    hard = kitti_difficulty_mask(boxes, occ, trunc, "hard")
    assert bool((moderate <= hard).all())
    custom = KittiDifficulty(min_height=0.0, max_occlusion=3, max_truncation=1.0)
    assert kitti_difficulty_mask(boxes, occ, trunc, custom).all()
    assert KITTI_DIFFICULTIES["moderate"] == KittiDifficulty(25.0, 1, 0.30)


def test_kitti_difficulty_mask_checks():
    with pytest.raises(ValueError, match="unknown KITTI difficulty 'medium'"):
        kitti_difficulty_mask(GT, T([0, 0]), T([0.0, 0.0]), "medium")
    with pytest.raises(ValueError, match="2 boxes, 1 occlusion codes"):
        kitti_difficulty_mask(GT, T([0]), T([0.0, 0.0]))
    assert kitti_difficulty_mask(torch.zeros(0, 4), T([]), T([])).shape == (0,)


def test_per_class_and_moderate_recall_hand_case():
    # image A: a car (GT 0) and a pedestrian (GT 1) against PROPS; top 2 at IoU 0.7:
    #   car best IoU 0.4 (missed), pedestrian 0.8 (hit).
    # image B: one car, matched with IoU 0.8 (hit), but largely occluded (not moderate).
    gt_b = T([[0.0, 0.0, 10.0, 10.0]])
    props_b = T([[0.0, 0.0, 10.0, 8.0]])
    gts, labels = [GT, gt_b], [T([0, 1]), T([0])]
    names = ("Car", "Pedestrian")
    r = recall_table([PROPS, props_b], gts, labels, names, ks=(2,), ious=(0.7,))
    assert r.per_class_at(2, 0.7) == {"Car": 0.5, "Pedestrian": 1.0}  # 1 of 2 cars, 1 of 1
    assert r.at(2, 0.7) == pytest.approx(2 / 3)  # micro: 2 of 3 objects
    assert r.at(2, 0.7, "mean") == 0.75

    # the moderate filter; boxes 10 px tall would fail the height rule, so use a
    # level with the KITTI occlusion/truncation bounds and no minimum height
    level = KittiDifficulty(min_height=0.0, max_occlusion=1, max_truncation=0.3)
    masks = [kitti_difficulty_mask(GT, T([0, 1]), T([0.0, 0.3]), level),
             kitti_difficulty_mask(gt_b, T([2]), T([0.0]), level)]
    assert [m.tolist() for m in masks] == [[True, True], [False]]
    gts_m, labels_m = select_objects(gts, labels, masks)
    assert [g.shape[0] for g in gts_m] == [2, 0] and labels_m[1].numel() == 0
    rm = recall_table([PROPS, props_b], gts_m, labels_m, names, ks=(2,), ious=(0.7,))
    assert rm.per_class_at(2, 0.7) == {"Car": 0.0, "Pedestrian": 1.0}
    assert rm.at(2, 0.7) == 0.5 and rm.num_objects == 2 and rm.num_images == 1

    # brute force: the same numbers from plain loops over brute_best_iou
    for (props, g, lab, m) in ((PROPS, GT, [0, 1], [True, True]), (props_b, gt_b, [0], [False])):
        best = brute_best_iou(props, g, 2)
        for b, c, keep in zip(best, lab, m):
            if keep:
                assert (b >= 0.7) == (rm.per_class_at(2, 0.7)[names[c]] == 1.0)


def test_select_objects_checks():
    with pytest.raises(ValueError, match="1 masks for 2"):
        select_objects([GT, GT], None, [T([True, True])])
    with pytest.raises(ValueError, match=r"masks\[0\] has 1 entries for 2 boxes"):
        select_objects([GT], None, [T([True])])
    gts, labels = select_objects([GT], None, [T([False, True])])
    assert labels is None and gts[0].tolist() == [GT[1].tolist()]


# -- how sure a recall figure is --------------------------------------------------------


def test_object_hits_agree_with_recall_table():
    torch.manual_seed(0)
    gts = [torch.rand(n, 2).mul(200).repeat(1, 2) + T([0.0, 0.0, 30.0, 40.0]) for n in (3, 0, 5)]
    props = [torch.rand(300, 2).mul(200).repeat(1, 2) + T([0.0, 0.0, 30.0, 40.0]) for _ in gts]
    hits = object_hits(props, gts, k=100, iou=0.5)
    assert [h.shape[0] for h in hits] == [3, 0, 5] and all(h.dtype == torch.bool for h in hits)
    found = sum(int(h.sum()) for h in hits)
    assert found / 8 == pytest.approx(recall_table(props, gts, ks=(100,), ious=(0.5,)).at(100, 0.5))
    with pytest.raises(ValueError, match="2 proposal lists for 3"):
        object_hits(props[:2], gts)


def test_sign_test_hand_values():
    assert sign_test(0, 0) == 1.0
    assert sign_test(5, 0) == pytest.approx(2 / 32)  # both tails of Bin(5, 1/2)
    assert sign_test(0, 5) == sign_test(5, 0)
    assert sign_test(10, 2) == pytest.approx(2 * (1 + 12 + 66) / 4096)
    assert sign_test(3, 3) == 1.0  # capped: the two tails overlap in the middle
    with pytest.raises(ValueError, match=">= 0"):
        sign_test(-1, 2)


def test_compare_recall_counts_each_side():
    a = [T([True, False, True]), T([], dtype=torch.bool), T([False, False])]
    b = [T([True, True, False]), T([], dtype=torch.bool), T([True, False])]
    c = compare_recall(a, b)
    assert (c.gained, c.lost, c.num_objects, c.net) == (2, 1, 5, 1)
    assert c.p_value == pytest.approx(sign_test(2, 1))
    assert compare_recall(a, a).p_value == 1.0 and compare_recall(a, a).net == 0
    with pytest.raises(ValueError, match="image 0"):
        compare_recall(a, [T([True]), a[1], a[2]])


def test_recall_interval_brackets_the_recall_and_narrows_with_more_frames():
    gen = torch.Generator().manual_seed(1)
    small = [torch.rand(4, generator=gen) < 0.7 for _ in range(20)]
    big = small * 9  # the same frames nine times: same recall, a narrower interval
    a, b = recall_interval(small), recall_interval(big)
    assert a.recall == pytest.approx(b.recall)
    assert a.low <= a.recall <= a.high and b.low <= b.recall <= b.high
    assert (b.high - b.low) < 0.6 * (a.high - a.low)  # ~1/3 as wide in theory
    assert (a.num_objects, a.num_images) == (80, 20)
    assert recall_interval(small, seed=3) == recall_interval(small, seed=3)  # seeded
    assert "95 % interval" in str(a)


def test_bootstrap_recalls_by_hand():
    """The frame bootstrap's draws: torch.randint of a generator seeded with ``seed``, rows of
    frame indices; micro recall pools a draw's objects whatever the class columns, balanced
    averages the recalls of the classes the draw holds; recall_interval takes its percentiles."""
    found = torch.tensor([[1.0, 0.0], [2.0, 1.0], [0.0, 0.0]], dtype=torch.float64)
    counts = torch.tensor([[1.0, 2.0], [3.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    draw = torch.randint(3, (50, 3), generator=torch.Generator().manual_seed(7))
    micro = bootstrap_recalls(found, counts, 50, 7)
    assert torch.equal(micro, bootstrap_recalls(found.sum(1, keepdim=True), counts.sum(1, keepdim=True), 50, 7))
    balanced = bootstrap_recalls(found, counts, 50, 7, balanced=True)
    for row, m, b in zip(draw.tolist(), micro.tolist(), balanced.tolist()):
        f, n = found[row].sum(0), counts[row].sum(0)
        assert m == pytest.approx(float(f.sum() / n.sum()))
        assert b == pytest.approx(float((f / n)[n > 0].mean()))
    hits = [T([True, False, False]), T([True, True, False, True]), T([False])]
    r = recall_interval(hits, samples=50, seed=7)
    q = torch.tensor([(1 - 0.95) / 2, (1 + 0.95) / 2], dtype=torch.float64)
    assert (r.low, r.high) == tuple(torch.quantile(micro, q).tolist())


def test_recall_interval_edge_cases():
    every = [T([True, True]), T([True])]
    r = recall_interval(every + [T([], dtype=torch.bool)])
    assert (r.recall, r.low, r.high, r.num_images) == (1.0, 1.0, 1.0, 2)  # the empty frame is left out
    with pytest.raises(ValueError, match="no ground-truth object"):
        recall_interval([T([], dtype=torch.bool)])
    with pytest.raises(ValueError, match="level"):
        recall_interval(every, level=1.0)
    with pytest.raises(ValueError, match="samples"):
        recall_interval(every, samples=0)
