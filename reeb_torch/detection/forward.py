"""One frame through the detector after its backbone: what ``GeneralizedRCNN.forward`` runs
after the backbone, on the same modules, for a frame whose backbone maps are computed
already (:mod:`reeb_torch.detection.feature_cache`).

:func:`frame_forward` runs the neck, ``model.rpn`` (a :class:`ReebRPN` handed the input image,
or the learned RPN), ``model.roi_heads`` and, in evaluation, its box head's passes and
``model.transform.postprocess`` back to input pixels; in training mode it returns the losses.
Detection (:func:`~reeb_torch.detection.inference.detect_images`) and the heads' training
(:mod:`reeb_torch.detection.head_training`) both go through it; it imports nothing of the
training.

Training-time ignore regions (:func:`drop_ignored`): proposals that overlap a ``DontCare``
box (more than half of the proposal's area inside it) or a neighbouring-class object
(``Van``, ``Person_sitting``; IoU >= 0.5), and no target with IoU >= 0.5, are not sampled as
background: KITTI's evaluation counts detections there as neither right nor wrong.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, ContextManager

import torch
from torch import Tensor, nn
from torchvision.models.detection.image_list import ImageList
from torchvision.models.detection.transform import resize_boxes
from torchvision.ops import box_iou
from torchvision.ops import boxes as box_ops

from .feature_cache import FrameFeatures
from .rpn import ReebRPN

__all__ = ["CachedFrame", "drop_ignored", "frame_forward"]


@dataclass
class CachedFrame:
    """One frame as the heads see it.

    Attributes:
        image: ``uint8 [3, H, W]``: what a :class:`ReebRPN` proposes from (by its digest).
        features: its cached frozen maps.
        boxes: ``float32 [N, 4]`` targets, input pixels; ``labels``: ``int64 [N]``, 1..C.
        ignore: ``[M, 4]`` neighbouring-class objects; ``dontcare``: ``[K, 4]`` DontCare boxes.
        mirror: the same frame flipped left to right (its own maps; boxes through
            :func:`mirror_boxes`), for ``TrainSettings.hflip``; ``None``: none.
    """

    image: Tensor
    features: FrameFeatures
    boxes: Tensor
    labels: Tensor
    ignore: Tensor = field(default_factory=lambda: torch.zeros(0, 4))
    dontcare: Tensor = field(default_factory=lambda: torch.zeros(0, 4))
    mirror: CachedFrame | None = None


def _ioa(a: Tensor, b: Tensor) -> Tensor:
    """``[len(a), len(b)]``: the share of each box of ``a``'s area inside each box of ``b``."""
    lt = torch.max(a[:, None, :2], b[None, :, :2])
    rb = torch.min(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)[:, None]
    return inter / area.clamp(min=1e-6)


def drop_ignored(proposals: Tensor, targets: Tensor, ignore: Tensor, dontcare: Tensor,
                 threshold: float = 0.5) -> Tensor:
    """The proposals (``[P, 4]``) that are not in an ignore region (module doc), all boxes
    in one frame; those with IoU >= ``threshold`` with a target are always kept."""
    if len(proposals) == 0 or (len(ignore) == 0 and len(dontcare) == 0):
        return proposals
    drop = torch.zeros(len(proposals), dtype=torch.bool)
    if len(ignore):
        drop |= box_iou(proposals, ignore).amax(1) >= threshold
    if len(dontcare):
        drop |= _ioa(proposals, dontcare).amax(1) > threshold
    if len(targets):
        drop &= box_iou(proposals, targets).amax(1) < threshold
    return proposals[~drop]


def _resized(boxes: Tensor, f: FrameFeatures) -> Tensor:
    """Boxes in input pixels, in the frame of ``f``'s maps (resized, ``f.top`` rows up)."""
    out = resize_boxes(boxes.float(), list(f.original_size), list(f.image_size))
    return out - out.new_tensor([0.0, f.top, 0.0, f.top]) if f.top else out


def _refined(heads: Any, logits: Tensor, deltas: Tensor, boxes: Tensor,
             size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """The next pass's input from a box-head pass over ``boxes``: the boxes some class scores
    ``heads.score_thresh`` or more on (the others could not be kept), their class
    probabilities ``[K, classes]`` and the box regressed for each one's most likely object
    class, clipped to ``size`` (``[K, 4]``)."""
    probs = torch.softmax(logits, -1)
    keep = (probs[:, 1:].amax(1) >= heads.score_thresh).nonzero().flatten()
    probs = probs[keep]
    decoded = heads.box_coder.decode(deltas[keep], [boxes[keep]])  # [K, classes, 4]
    best = probs[:, 1:].argmax(1) + 1
    return probs, box_ops.clip_boxes_to_image(decoded[torch.arange(len(keep)), best], size)


def frame_forward(model: nn.Module, frame: CachedFrame, proposals: Tensor | None = None,
                  clock: Callable[[str], ContextManager[Any]] | None = None, passes: int = 1) -> dict[str, Tensor]:
    """One frame through neck, proposals and box head: the losses in training mode, the
    detections (``boxes`` in input pixels, ``labels``, ``scores``) in evaluation mode.

    ``proposals``: the frame's REEB boxes (input pixels, best first) where they are known
    already; otherwise a :class:`ReebRPN` proposes from ``frame.image`` (or reads its
    cache). The heads work in the frame of the maps: the resized image less its top
    ``frame.features.top`` rows. ``clock(stage)``: a context that times each stage of the
    evaluation (``neck``, ``roi_align``, ``box_head``, ``postprocess``;
    :class:`~reeb_torch.detection.inference.StageClock`). ``passes``: in evaluation, the box
    head's passes: each after the first pools the boxes the last one regressed (each box for
    its most likely class) and averages its class probabilities with the earlier passes',
    over the boxes some class scores ``score_thresh`` or more on (the others are dropped:
    their scores are below what detection keeps)."""
    stage = clock or (lambda name: nullcontext())
    f = frame.features
    det: Any = model  # a detector: nn.Module leaves its parts (transform, backbone, ...) untyped
    with stage("neck"):
        features = det.backbone.neck({k: v[None] for k, v in f.levels.items()})
    (h, w), top = f.image_size, f.top
    images = ImageList(torch.zeros(()).expand(1, 3, *f.padded_size), [(h - top, w)])
    targets = None
    if det.training:
        targets = [{"boxes": _resized(frame.boxes, f), "labels": frame.labels}]
    rpn_losses: dict[str, Tensor] = {}
    if isinstance(det.rpn, ReebRPN):
        boxes = proposals if proposals is not None else det.rpn.propose([frame.image])[0]
        placed = [det.rpn.place(boxes.to(features["0"].device), f.original_size, f.image_size, top)]
    else:
        placed, rpn_losses = det.rpn(images, features, targets)
    if targets is not None:
        placed = [drop_ignored(placed[0], targets[0]["boxes"], _resized(frame.ignore, f), _resized(frame.dontcare, f))]
        _, roi_losses = det.roi_heads(features, placed, images.image_sizes, targets)
        return {**rpn_losses, **roi_losses}
    heads = det.roi_heads  # RoIHeads.forward's evaluation path for boxes, stage by stage
    low = getattr(det.backbone, "precision", "float32") == "bfloat16"  # the box head's products too
    logits = deltas = probs = torch.empty(0)
    for n in range(passes):
        if n:  # another pass over the boxes the last one regressed, its class scores averaged in
            kept, refined = _refined(heads, logits, deltas, placed[0], images.image_sizes[0])
            if not len(refined):
                break
            probs, placed = kept, [refined]
        with stage("roi_align"):
            pooled = heads.box_roi_pool(features, placed, images.image_sizes)
        with stage("box_head"), torch.autocast(pooled.device.type, torch.bfloat16, enabled=low):
            logits, deltas = (t.float() for t in heads.box_predictor(heads.box_head(pooled)))
            if n:
                logits = torch.log((probs * n + torch.softmax(logits, -1)) / (n + 1))
    with stage("postprocess"):
        boxes, scores, labels = heads.postprocess_detections(logits, deltas, placed, images.image_sizes)
        found = boxes[0] + boxes[0].new_tensor([0.0, top, 0.0, top]) if top else boxes[0]
        detections = [{"boxes": found, "labels": labels[0], "scores": scores[0]}]
        return det.transform.postprocess(detections, [(h, w)], [tuple(f.original_size)])[0]
