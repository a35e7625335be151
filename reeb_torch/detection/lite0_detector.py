"""Faster R-CNN on a frozen, pretrained EfficientNet-Lite0, with REEB (or learned) proposals.

:func:`reeb_fasterrcnn_lite0` builds torchvision's
:class:`~torchvision.models.detection.FasterRCNN` as the design asks for it:

- **backbone** :class:`Lite0Pyramid`: EfficientNet-Lite0 with its ImageNet weights
  (:mod:`reeb_torch.detection.lite0`), frozen (``eval`` mode, no gradients), giving the
  maps of strides 8, 16 and 32 (40, 112, 320 channels), then a light trainable neck
  (:class:`LiteNeck`: a 1×1 lateral conv per level to ``neck_channels`` and FPN's top-down
  sum, without FPN's 3×3 output convs, whose cost on the stride-8 map would dominate
  training on a CPU);
- **proposals** :class:`~reeb_torch.detection.ReebRPN` (REEB, or any training-free
  source given as ``generator``), or torchvision's learned RPN (``proposals="learned"``,
  the control: 2 anchor sizes × 3 aspect ratios per level, sizes 32-1024 px);
- **RoI pooling** :class:`~torchvision.ops.MultiScaleRoIAlign` (7×7, sampling ratio 2) over
  the three levels (:class:`~reeb_torch.detection.roi_align.PyramidRoIAlign`: compiled for
  inference on the CPU), torchvision's two-layer box head (:class:`TwoMLPHead`,
  ``representation_size`` units) and box predictor.

The frozen body is :class:`~reeb_torch.detection.lite0.FrozenLite0` (BatchNorm folded,
channels-last) in ``float32`` or ``bfloat16``.

Both arms build the same modules in the same order, so with the same ``torch`` seed the neck
and the box head start from the same weights. Images enter as float RGB in [0, 1]; the
transform resizes them to a shorter side of ``min_size`` (KITTI's 1242×375 becomes
1907×576 by default: objects of the moderate level, 25 px tall, become 38 px, five cells of
the stride-8 map) and normalises them as the Lite models expect.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.rpn import RPNHead

from ..config import ReebConfig
from .box_head import LowRankLinear, quantise_box_head
from .lite0 import LITE0_MEAN, LITE0_STD, PYRAMID_LEVELS, EfficientNetLite0, FrozenLite0, load_lite0
from .roi_align import PyramidRoIAlign
from .rpn import ReebRPN

__all__ = ["LiteNeck", "Lite0Pyramid", "reeb_fasterrcnn_lite0", "LEARNED_ANCHOR_SIZES"]

LEARNED_ANCHOR_SIZES = ((32, 64), (128, 256), (512, 1024))
"""Anchor sizes (px of the resized image) of the learned RPN on the three levels."""


class LiteNeck(nn.Module):
    """Trainable 1×1 laterals and FPN's top-down pathway over the frozen maps.

    ``forward(levels)``: ``{"0": [B, 40, h0, w0], "1": [B, 112, h1, w1], "2": [B, 320, h2,
    w2]}`` (any float dtype) -> the same names, each ``[B, channels, h_i, w_i]`` float32:
    ``P2 = L2(C2)``, ``P1 = L1(C1) + up(P2)``, ``P0 = L0(C0) + up(P1)`` (nearest upsampling
    to the finer map's size).
    """

    def __init__(self, channels: int = 128) -> None:
        super().__init__()
        self.lateral = nn.ModuleDict({name: nn.Conv2d(c, channels, 1)
                                      for name, (_, _, c) in PYRAMID_LEVELS.items()})
        self.out_channels = channels

    def forward(self, levels: dict[str, Tensor]) -> "OrderedDict[str, Tensor]":
        names = list(PYRAMID_LEVELS)
        out: dict[str, Tensor] = {}
        above: Tensor | None = None
        for name in reversed(names):
            x = self.lateral[name](levels[name].float())
            if above is not None:
                x = x + F.interpolate(above, size=x.shape[-2:], mode="nearest")
            out[name] = above = x
        return OrderedDict((n, out[n]) for n in names)


class Lite0Pyramid(nn.Module):
    """The detector's backbone: frozen EfficientNet-Lite0 maps, then :class:`LiteNeck`.

    ``forward(x)``: ``x`` ``[B, 3, H, W]`` normalised (:data:`LITE0_MEAN`, :data:`LITE0_STD`)
    -> ``OrderedDict`` of three ``[B, out_channels, ceil(H/s), ceil(W/s)]`` maps, s = 8, 16, 32.
    :meth:`frozen` is the part computed once per frame and cached (:class:`FrozenLite0` in
    ``precision``); the body stays in ``eval`` mode whatever ``train()`` is called with.
    """

    def __init__(self, body: EfficientNetLite0, channels: int = 128, precision: str = "float32") -> None:
        super().__init__()
        self.body = FrozenLite0(body, precision)
        self.neck = LiteNeck(channels)
        self.out_channels = channels

    def train(self, mode: bool = True) -> "Lite0Pyramid":
        super().train(mode)
        self.body.eval()
        return self

    @property
    def precision(self) -> str:
        """The precision the frozen body computes in (``float32`` or ``bfloat16``)."""
        return self.body.precision

    @torch.no_grad()
    def frozen(self, x: Tensor) -> dict[str, Tensor]:
        """The body's maps (:meth:`EfficientNetLite0.pyramid`, in :attr:`precision`,
        channels-last), without gradients."""
        return self.body(x)

    def forward(self, x: Tensor) -> "OrderedDict[str, Tensor]":
        return self.neck(self.frozen(x))


def _learned_rpn_parts(channels: int) -> tuple[AnchorGenerator, RPNHead]:
    ratios = ((0.5, 1.0, 2.0),) * len(LEARNED_ANCHOR_SIZES)
    anchors = AnchorGenerator(LEARNED_ANCHOR_SIZES, ratios)
    return anchors, RPNHead(channels, anchors.num_anchors_per_location()[0])


def reeb_fasterrcnn_lite0(
    num_classes: int,
    *,
    proposals: Literal["reeb", "learned"] = "reeb",
    generator: nn.Module | None = None,
    config: ReebConfig | None = None,
    weights: str | os.PathLike | None = None,
    min_size: int = 576,
    max_size: int = 2048,
    neck_channels: int = 128,
    representation_size: int = 1024,
    box_head_rank: int = 0,
    box_head_int8: bool = False,
    precision: str = "float32",
    top_k_train: int = 2000,
    top_k_test: int = 1000,
    **kwargs: Any,
) -> FasterRCNN:
    """Faster R-CNN, frozen pretrained EfficientNet-Lite0, REEB (or learned) proposals.

    Args:
        num_classes: classes *including* the background (label 0); KITTI's Car,
            Pedestrian, Cyclist: ``num_classes=4``, labels 1..3.
        proposals: ``"reeb"``: a :class:`ReebRPN`, attached, running ``generator`` (default
            ``ProposalGenerator(config)``); ``"learned"``: torchvision's RPN on the neck.
        generator: any module with the :class:`~reeb_torch.ProposalGenerator` contract
            (e.g. one serving another method's stored proposals).
        config: REEB settings when ``generator`` is ``None`` (default: ``ReebConfig()``).
        weights: the Lite0 state dict (default: the ``detect`` extra's file); ImportError
            naming the extra when it is missing.
        min_size, max_size: the transform's resize (shorter side, bound on the longer).
        neck_channels: channels of the neck and of the pooled RoI features.
        representation_size: units of each of the box head's two layers.
        box_head_rank: 0: the box head's first layer in full; R: as two layers through R units
            (:class:`~reeb_torch.detection.box_head.LowRankLinear`, what
            :func:`~reeb_torch.detection.box_head.factorise_box_head` makes of a trained one).
        box_head_int8: the box head's layers as :class:`~reeb_torch.detection.box_head.
            Int8Linear` (to be loaded with a quantised head's weights; not trainable).
        precision: the frozen body's (``"float32"`` or ``"bfloat16"``; :class:`FrozenLite0`).
        top_k_train, top_k_test: proposals per image handed to the box head in training and
            evaluation, for either arm (torchvision's ``rpn_post_nms_top_n_train``/``_test``).
        **kwargs: passed to :class:`FasterRCNN` (``box_batch_size_per_image``,
            ``box_score_thresh``, ``box_detections_per_img``, ...).

    Returns:
        The model; ``model(images)`` in ``eval`` mode gives ``{"boxes", "labels",
        "scores"}`` per image in its input pixels.
    """
    if proposals not in ("reeb", "learned"):
        raise ValueError(f"proposals must be 'reeb' or 'learned', got {proposals!r}")
    backbone = Lite0Pyramid(load_lite0(weights), neck_channels, precision)
    anchors, rpn_head = _learned_rpn_parts(neck_channels)
    model = FasterRCNN(
        backbone, None, min_size=min_size, max_size=max_size,
        image_mean=list(LITE0_MEAN), image_std=list(LITE0_STD),
        rpn_anchor_generator=anchors, rpn_head=rpn_head,
        rpn_pre_nms_top_n_train=top_k_train, rpn_pre_nms_top_n_test=top_k_test,
        rpn_post_nms_top_n_train=top_k_train, rpn_post_nms_top_n_test=top_k_test,
        box_roi_pool=PyramidRoIAlign(list(PYRAMID_LEVELS), output_size=7, sampling_ratio=2),
        box_head=TwoMLPHead(neck_channels * 7 * 7, representation_size),
        box_predictor=FastRCNNPredictor(representation_size, num_classes),
        **kwargs,
    )
    if box_head_rank:
        head: Any = model.roi_heads.box_head
        head.fc6 = LowRankLinear(head.fc6.in_features, head.fc6.out_features, box_head_rank)
    if box_head_int8:
        quantise_box_head(model)
    if proposals == "reeb":
        ReebRPN(config, generator=generator, top_k_train=top_k_train, top_k_test=top_k_test,
                image_mean=LITE0_MEAN, image_std=LITE0_STD).attach(model)
    return model
