"""KITTI's 2D AP|R40 (reeb_torch.metrics.kitti_ap) against hand-worked examples and, where the
two protocols must agree, torchmetrics' COCO-style AP on the same boxes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reeb_torch.datasets.kitti import KittiObject
from reeb_torch.metrics.kitti_ap import (
    average_precision,
    bootstrap,
    evaluate,
    frame_stats,
    get_thresholds,
    kitti_ap,
)


def obj(kind: str, box, occluded: int = 0, truncated: float = 0.0) -> KittiObject:
    return KittiObject(kind, truncated, occluded, 0.0, tuple(float(v) for v in box), (1.5, 1.6, 4.0),
                       (0.0, 1.6, 20.0), 0.0)


A, B = (100, 100, 200, 180), (300, 100, 380, 160)
VAN, SMALL, DONTCARE = (500, 100, 600, 180), (700, 100, 740, 120), (800, 50, 1000, 150)


def test_one_frame_by_hand():
    """Each rule once: a Van and a 20-px car are ignored objects, a box inside DontCare and a
    detection lower than 25 px are no false positives, a duplicate is one."""
    objects = [obj("Car", A), obj("Car", B), obj("Van", VAN), obj("Car", SMALL),
               obj("DontCare", DONTCARE), obj("Pedestrian", (50, 50, 70, 120))]
    dets = np.array([A, VAN, (820, 60, 900, 140), (50, 250, 150, 330), B, SMALL, (102, 101, 201, 182)], float)
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])
    s = frame_stats(objects, dets, scores, "Car")
    assert s.num_gt == 2
    assert sorted(s.tp_scores.tolist()) == [0.5, 0.9]
    # (tp, fp, fn) keeping the scores >= t
    counts = s.at(np.array([0.95, 0.9, 0.6, 0.5, 0.3])).tolist()
    assert counts == [[0, 0, 2], [1, 0, 1], [1, 1, 1], [2, 1, 0], [2, 2, 0]]


def test_hard_objects_are_ignored_not_missed():
    objects = [obj("Car", A, occluded=2), obj("Car", B, truncated=0.5), obj("Car", (0, 0, 50, 25))]
    s = frame_stats(objects, np.array([A, B], float), np.array([0.9, 0.8]), "Car")
    assert s.num_gt == 0 and s.at(np.array([0.0])).tolist() == [[0, 0, 0]]


def test_thresholds_by_hand():
    # 2 objects: one threshold per true positive
    assert get_thresholds(np.array([0.5, 0.9]), 2).tolist() == [0.9, 0.5]
    # 80 objects: the first, then every second true positive (recall steps of 1/40)
    scores = np.linspace(1.0, 0.21, 80)
    t = get_thresholds(scores, 80)
    assert len(t) == 41 and t[0] == scores[0]
    np.testing.assert_array_equal(t[1:], scores[1::2])


def grid_frames(n: int, fp_after: int, n_fp: int, shift: float = 0.0):
    """``n`` cars in frames of 10, detected exactly (or shifted by ``shift`` px) with falling
    scores; ``n_fp`` false positives ranked right after the ``fp_after``-th true positive."""
    objects, dets = [], []
    score = iter(np.linspace(1.0, 0.1, n + n_fp))
    for f in range(math.ceil(n / 10)):
        objects.append([obj("Car", (60 * i, 100, 60 * i + 50, 150)) for i in range(min(10, n - 10 * f))])
        dets.append({"boxes": [], "scores": [], "labels": []})
    for k in range(n):
        f, i = divmod(k, 10)
        d = dets[f]
        d["boxes"].append((60 * i + shift, 100, 60 * i + 50 + shift, 150))
        d["scores"].append(next(score))
        if k + 1 == fp_after:
            for _ in range(n_fp):
                d["boxes"].append((60 * i, 300, 60 * i + 50, 350))
                d["scores"].append(next(score))
    for d in dets:
        d["labels"] = [0] * len(d["boxes"])
        d.update({k: torch.tensor(v, dtype=torch.float64) for k, v in d.items() if k != "labels"})
        d["labels"] = torch.tensor(d["labels"])
    return objects, dets


def test_ap_by_hand():
    """80 cars, 20 false positives ranked after the 40th hit: the 41 thresholds sit at 1, 2,
    4, ..., 80 hits; precision is 1 up to 40 hits and at most 80/100 after, so AP|R40 =
    (20 x 1 + 20 x 0.8) / 40 = 0.9 (index 0 is left out)."""
    objects, dets = grid_frames(80, fp_after=40, n_fp=20)
    stats = evaluate(objects, dets, ("Car",))
    assert average_precision(stats["Car"]) == pytest.approx(0.9)
    perfect = evaluate(*grid_frames(80, fp_after=0, n_fp=0), ("Car",))
    assert average_precision(perfect["Car"]) == pytest.approx(1.0)
    # IoU 0.7 for cars: a shift of 5 px (IoU 0.82) still hits, 10 px (0.67) does not
    assert average_precision(evaluate(*grid_frames(80, 0, 0, shift=5), ("Car",))["Car"]) == 1.0
    assert average_precision(evaluate(*grid_frames(80, 0, 0, shift=10), ("Car",))["Car"]) == 0.0


def alternating(n: int, fp_per_hit: int):
    """Every hit preceded by ``fp_per_hit`` higher-scoring false positives: precision is
    exactly 1 / (1 + fp_per_hit) at every recall."""
    objects, dets = [], []
    s = iter(np.linspace(1.0, 0.01, n * (1 + fp_per_hit)))
    for f in range(n // 10):
        objects.append([obj("Car", (60 * i, 100, 60 * i + 50, 150)) for i in range(10)])
        boxes, scores = [], []
        for i in range(10):
            for j in range(fp_per_hit):
                boxes.append((60 * i, 250 + 60 * j, 60 * i + 50, 300 + 60 * j))
                scores.append(next(s))
            boxes.append((60 * i, 100, 60 * i + 50, 150))
            scores.append(next(s))
        dets.append({"boxes": torch.tensor(boxes), "scores": torch.tensor(scores),
                     "labels": torch.zeros(len(boxes), dtype=torch.int64)})
    return objects, dets


def coco_ap(objects, dets) -> float:
    from torchmetrics.detection import MeanAveragePrecision

    metric = MeanAveragePrecision(iou_type="bbox", iou_thresholds=[0.7], backend="pycocotools")
    metric.update([{k: d[k].float() for k in ("boxes", "scores")} | {"labels": d["labels"]} for d in dets],
                  [{"boxes": torch.tensor([o.box for o in objs]), "labels": torch.zeros(len(objs), dtype=torch.int64)}
                   for objs in objects])
    return float(metric.compute()["map"])


@pytest.mark.parametrize("case", ["perfect", "half", "third", "missed"])
def test_agrees_with_torchmetrics_where_precision_is_flat(case):
    """Where interpolated precision is the same at every recall (and nothing is ignored, all
    objects moderate, fewer than 100 detections a frame), the 40-point and COCO's 101-point
    averages are that precision: the two must agree."""
    pytest.importorskip("torchmetrics")
    pytest.importorskip("pycocotools")
    objects, dets = {"perfect": lambda: grid_frames(80, 0, 0), "half": lambda: alternating(80, 1),
                     "third": lambda: alternating(80, 2), "missed": lambda: grid_frames(80, 0, 0, shift=10)}[case]()
    ours = average_precision(evaluate(objects, dets, ("Car",))["Car"])
    expected = {"perfect": 1.0, "half": 0.5, "third": 1 / 3, "missed": 0.0}[case]
    assert ours == pytest.approx(expected, abs=1e-9)
    assert coco_ap(objects, dets) == pytest.approx(ours, abs=1e-6)


def test_map_and_bootstrap():
    objects, dets = grid_frames(80, fp_after=40, n_fp=20)
    stats = evaluate(objects, dets, ("Car", "Pedestrian"))
    ap = kitti_ap(stats)
    assert math.isnan(ap["Pedestrian"]) and ap["mAP"] == pytest.approx(0.9)
    low, high = bootstrap(stats, samples=200)["Car"]
    assert 0.0 <= low <= high <= 1.0
    assert math.isnan(bootstrap(stats, samples=20)["Pedestrian"][0])
