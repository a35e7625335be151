"""The detection benchmark: its proposal sources, their per-frame store, and its table.

References: a stub source that counts its calls (a stored frame is not computed twice),
entries stored for another key (refused), and the benchmark run end to end on the bundled
frames with a tiny budget.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

from reeb_torch.detection import StaleCacheError, image_digest

from tests.detection.test_detection import frames, lite0, random_boxes  # noqa: F401  (fixtures)
from tests.eval.test_eval import _example_kitti

ROOT = Path(__file__).resolve().parents[2]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def sources():
    return _script("_detection_sources")


def stub_source(sources, name: str = "stub"):
    """A proposal source that returns a fixed set of boxes of each image, and counts calls."""
    calls = []

    def fn(image):
        calls.append(tuple(image.shape))
        h, w = image.shape[-2:]
        boxes = torch.cat([random_boxes(h, w, 40, seed=3), torch.tensor([[388.0, 182, 424, 203]])])
        return {"boxes": boxes, "scores": torch.linspace(1, 0, len(boxes))}

    return sources.ProposalSource(name, f"{name}-v1", fn), calls


def test_proposal_store_computes_once_and_refuses_other_keys(sources, frames, tmp_path):
    source, calls = stub_source(sources)
    first = sources.cached_proposals(frames, source, tmp_path, progress=False)
    again = sources.SourceGenerator(source, tmp_path)([f["image"].float() / 255 for f in frames])
    assert len(calls) == 2  # the second pass reads the store, float images included
    assert all(torch.equal(a, b["boxes"]) for a, b in zip(first, again))
    digest = image_digest(frames[0]["image"])
    other = sources.ProposalStore(tmp_path, "other-v2")
    other.folder.mkdir(parents=True)
    shutil.copy(sources.ProposalStore(tmp_path, source.key).path(digest), other.path(digest))
    with pytest.raises(StaleCacheError):
        other.load(digest, (375, 1242))


def test_unknown_and_unavailable_sources(sources):
    from reeb_torch import PRESETS

    with pytest.raises(ValueError, match="unknown proposal source"):
        sources.make_source("bing-ish")
    if "training-free" not in PRESETS:
        with pytest.raises(sources.SourceUnavailable):
            sources.make_source("training-free")


def test_detection_benchmark_writes_its_table(lite0, tmp_path):
    bench = _script("detection")
    data = _example_kitti(tmp_path / "kitti")
    out = tmp_path / "out"
    bench.main(["--train", str(data), "--test", str(data), "--proposals", "reeb", "rpn", "--out", str(out),
                "--cache", str(tmp_path / "cache"), "--max-steps", "2", "--min-size", "128", "--max-size", "448",
                "--rois", "32", "--proposals-train", "100", "--proposals-test", "50", "--bootstrap", "20"])
    summary = json.loads((out / "detection.json").read_text())
    assert set(summary) == {"reeb", "rpn"}
    for arm in summary.values():
        assert set(arm) == {"Car", "Pedestrian", "Cyclist", "mAP", "train_s"}
        assert arm["Car"] is not None and 0.0 <= arm["Car"] <= 100.0
    details = json.loads((out / "detection_details.json").read_text())
    assert details["command"].startswith("python benchmarks/detection.py --train")
