"""The MobileNetV3 detector of benchmarks/rpn_arms.py (benchmarks/_mobilenet.py): REEB's
proposals against torchvision's learned RPN in one network, and the script end to end.

References: the learned arm's initial weights (the REEB arm must start from the same ones),
a local state dict loaded back tensor for tensor, and a short training whose loss must fall.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest
import torch

from reeb_torch.detection import ReebRPN

from tests.detection.test_detection import CLASSES, EXAMPLES, FRAMES, SMALL, cache, config, frames, model_inputs  # noqa: F401  (fixtures)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
try:
    import rpn_arms as script
    from _mobilenet import reeb_fasterrcnn_mobilenet_v3
finally:
    sys.path.pop(0)


# -- the MobileNetV3 detector on real REEB proposals -----------------------------------------


def test_training_step_runs_reeb_and_gives_finite_losses(frames, config):
    torch.manual_seed(0)
    model = reeb_fasterrcnn_mobilenet_v3(len(CLASSES) + 1, config=config, **SMALL)
    assert isinstance(model.rpn, ReebRPN)
    model.train()
    images, targets = model_inputs(frames)
    losses = model(images, targets)
    assert set(losses) == {"loss_classifier", "loss_box_reg"}  # REEB adds no loss
    assert all(torch.isfinite(v) for v in losses.values())
    sum(losses.values()).backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_learned_arm_is_the_same_network_with_torchvision_rpn(frames):
    torch.manual_seed(0)
    learned = reeb_fasterrcnn_mobilenet_v3(5, proposals="learned", **SMALL)
    torch.manual_seed(0)
    reeb = reeb_fasterrcnn_mobilenet_v3(5, **SMALL)
    sd_learned, sd_reeb = learned.state_dict(), reeb.state_dict()
    assert set(sd_reeb) == {k for k in sd_learned if not k.startswith("rpn.")}
    assert all(torch.equal(sd_reeb[k], sd_learned[k]) for k in sd_reeb)  # same initial weights
    learned.train()
    losses = learned(*model_inputs(frames))
    assert {"loss_objectness", "loss_rpn_box_reg"} <= set(losses)


def test_evaluation_returns_detections_in_input_pixels(frames, cache, config):
    torch.manual_seed(0)
    model = reeb_fasterrcnn_mobilenet_v3(5, config=config, cache=cache, box_score_thresh=0.0,
                                         **SMALL).eval()
    images, _ = model_inputs(frames)
    with torch.no_grad():
        out = model(images)
    for image, det in zip(images, out):
        h, w = image.shape[-2:]
        b = det["boxes"]
        assert b.shape[1] == 4 and len(b) > 0
        assert (b[:, 0] >= 0).all() and (b[:, 2] <= w).all() and (b[:, 3] <= h).all()
        assert b[:, 2].max() > 424 or b[:, 3].max() > 128  # not the 424×128 model frame
        assert set(det) == {"boxes", "labels", "scores"}


@pytest.mark.slow
def test_short_training_on_two_frames_overfits(frames, cache, config):
    """From scratch, cached REEB proposals: the loss falls by half or more in 20 steps."""
    torch.manual_seed(0)
    model = reeb_fasterrcnn_mobilenet_v3(5, config=config, cache=cache, **dict(SMALL, min_size=96))
    model.train()
    images, targets = model_inputs(frames)
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    history = []
    for _ in range(20):
        loss = sum(model(images, targets).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(loss.item())
    first, last = sum(history[:3]) / 3, sum(history[-3:]) / 3
    assert last <= 0.5 * first, history


# -- backbone weights --------------------------------------------------------------------------


def test_backbone_weights_from_a_local_file(tmp_path):
    from torchvision.models import mobilenet_v3_large

    torch.manual_seed(1)
    reference = mobilenet_v3_large(weights=None)
    path = tmp_path / "mobilenet_v3_large.pt"
    torch.save(reference.state_dict(), path)
    torch.manual_seed(2)
    model = reeb_fasterrcnn_mobilenet_v3(5, backbone_weights=path, **SMALL)
    body = model.backbone.body.state_dict()
    ref = reference.features.state_dict()
    for k, v in body.items():
        if not k.endswith("num_batches_tracked"):
            assert torch.equal(v, ref[k]), k
    torch.save({"something": torch.zeros(3)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="features"):
        reeb_fasterrcnn_mobilenet_v3(5, backbone_weights=tmp_path / "bad.pt", **SMALL)


# -- the REEB-against-a-learned-RPN experiment (benchmarks/rpn_arms.py) -----------------------------------------------------------------------


@pytest.mark.slow
def test_train_script_trains_checkpoints_and_resumes(tmp_path):
    data = tmp_path / "kitti"
    for sub in ("images", "labels"):
        (data / sub).mkdir(parents=True)
    for i, stem in enumerate(FRAMES + FRAMES[:1]):
        shutil.copy(EXAMPLES / f"{stem}.png", data / "images" / f"{i:06d}.png")
        shutil.copy(EXAMPLES / f"{stem}.txt", data / "labels" / f"{i:06d}.txt")
    common = ["--data", str(data), "--train-frames", "2", "--out", str(tmp_path / "run"),
              "--min-size", "96", "--max-size", "640", "--box-batch-size", "32", "--proposals-train", "100",
              "--proposals-test", "50", "--recall-ks", "50,100", "--warmup", "1",
              "--checkpoint-every", "1", "--preset", "default"]
    with pytest.raises(SystemExit, match="--data .*nothing"):
        script.main(["--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")])
    first = script.main(common + ["--iterations", "2"])
    assert (tmp_path / "run" / "last.pt").exists() and (tmp_path / "run" / "reeb_cache.pt").exists()
    assert first["val_frames"] == 1 and set(first["AP50_per_class"]) == set(CLASSES)
    assert 0.0 <= first["recall"]["micro"]["100"]["0.5"] <= 1.0
    script.main(common + ["--iterations", "3", "--resume"])
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)  # tensors and plain values only
    assert ckpt["iteration"] == 3 and [h["iteration"] for h in ckpt["history"]] == [1, 2, 3]
    # a checkpoint from elsewhere that runs code when unpickled in full: refused, never run
    torch.save({"model": _RunsCode(tmp_path / "ran")}, tmp_path / "run" / "last.pt")
    with pytest.raises(SystemExit, match="not a checkpoint of this script"):
        script.main(common + ["--iterations", "4", "--resume"])
    assert not (tmp_path / "ran").exists()


class _RunsCode:
    """Unpickled in full, it creates the file ``path``: what a hostile checkpoint could do."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return open, (str(self.path), "w")
