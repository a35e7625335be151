"""Training the detector's heads over cached backbone features, and detecting with them.

With the backbone frozen (:func:`~reeb_torch.detection.reeb_fasterrcnn_lite0`), one step
needs only the cached maps of its frames (:mod:`reeb_torch.detection.feature_cache`). For
each frame, :func:`frame_forward` runs what ``GeneralizedRCNN.forward`` runs after the
backbone, on the same modules: the neck, ``model.rpn`` (a :class:`ReebRPN` handed the input
image, or the learned RPN), ``model.roi_heads``, and in evaluation
``model.transform.postprocess`` back to input pixels. Frames go through one at a time (a
batch's frames differ in size; one at a time, each frame's maps are exactly those of the
frame alone) and a step's gradient is the mean over its frames.

Training-time ignore regions: proposals that overlap a ``DontCare`` box (more than half of
the proposal's area inside it) or a neighbouring-class object (``Van``, ``Person_sitting``;
IoU >= 0.5), and no target with IoU >= 0.5, are not sampled as background: KITTI's
evaluation counts detections there as neither right nor wrong.

Augmentation (``TrainSettings.hflip``): each frame of a step is replaced by its mirror image
with probability 1/2 — a :class:`CachedFrame` of the horizontally flipped image, with its own
cached maps and proposals (:func:`mirror_boxes` flips the targets), since a frozen
backbone's maps of a flipped image are not the flipped maps.

Deterministic for a seed: the frame order and the mirror draws come from their own
generator, the RoI and anchor samplers from ``torch.manual_seed(seed)`` set at the start.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, ContextManager, cast

import torch
from torch import Tensor, nn
from torchvision.models.detection.image_list import ImageList
from torchvision.models.detection.transform import resize_boxes
from torchvision.ops import box_iou
from torchvision.ops import boxes as box_ops

from .feature_cache import FrameFeatures
from .rpn import ReebRPN

__all__ = ["TrainSettings", "CachedFrame", "mirror_boxes", "drop_ignored", "frame_forward", "train_heads", "detect"]


@dataclass(frozen=True)
class TrainSettings:
    """The training budget and optimiser.

    Attributes:
        epochs: passes over the training frames.
        batch_size: frames per step.
        lr: AdamW's peak learning rate (linear warm-up over ``warmup`` steps, then cosine
            decay to 1 % of it).
        weight_decay: AdamW's decoupled weight decay.
        warmup: warm-up steps.
        seed: seeds the frame order and torch's global generator (the samplers).
        max_steps: stop after this many steps (``None``: ``epochs`` full passes).
        hflip: train on each frame's :attr:`CachedFrame.mirror` instead of the frame with
            probability 1/2 (every frame must have one).
        factorised_epochs: with a ``box_head_rank``: once the full box head is trained and its
            first layer factorised, the heads train this many more passes from there (peak
            learning rate ``lr / 10``; 0: the factorised layer as the SVD gives it).
    """

    epochs: int = 12
    batch_size: int = 2
    lr: float = 3e-4
    weight_decay: float = 1e-4
    warmup: int = 50
    seed: int = 0
    max_steps: int | None = None
    hflip: bool = False
    factorised_epochs: int = 0

    def tuning(self) -> "TrainSettings":
        """The settings of the passes after factorising (:attr:`factorised_epochs`)."""
        return dataclasses.replace(self, epochs=self.factorised_epochs, lr=self.lr / 10, max_steps=None,
                                   warmup=min(self.warmup, 10), factorised_epochs=0)


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


def mirror_boxes(boxes: Tensor, width: int) -> Tensor:
    """``[N, 4]`` ``(x1, y1, x2, y2)`` boxes of an image ``width`` pixels wide, as they lie in
    the image flipped left to right: ``(width − x2, y1, width − x1, y2)``."""
    return torch.stack([width - boxes[:, 2], boxes[:, 1], width - boxes[:, 0], boxes[:, 3]], 1)


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


def _lr(step: int, total: int, s: TrainSettings) -> float:
    if step < s.warmup:
        return s.lr * (step + 1) / s.warmup
    t = (step - s.warmup) / max(1, total - s.warmup)
    return s.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(1.0, t))))


def _step(model: nn.Module, frames: Sequence[CachedFrame], optimizer: torch.optim.Optimizer) -> float:
    """One optimiser step on ``frames`` (gradient = mean over the frames); the mean loss."""
    optimizer.zero_grad(set_to_none=True)
    total = 0.0
    for frame in frames:
        proposals = getattr(frame, "proposals", None)  # a StoredFrame's, read from its cache
        loss = cast(Tensor, sum(frame_forward(model, frame, proposals).values())) / len(frames)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite training loss {loss.item()}")
        loss.backward()
        total += loss.item()
    optimizer.step()
    return total


CHECKPOINT_STEPS = 250
"""Besides each epoch's end, :func:`train_heads` keeps its state every this many steps (an
epoch of a large data set is long)."""


def train_heads(model: nn.Module, frames: Sequence[CachedFrame], settings: TrainSettings = TrainSettings(),
                progress: bool = True, checkpoint: Any = None) -> dict[str, object]:
    """Train every parameter of ``model`` that requires a gradient (the neck, the box head
    and predictor, the learned RPN's head; the frozen backbone has none) over ``frames``
    (:class:`CachedFrame`, or :class:`~reeb_torch.detection.fitting.StoredFrame` read from disk).

    ``checkpoint`` (a :class:`~reeb_torch.ranker.store.CheckpointSlot`): the training state
    (weights, optimiser, generators, step, losses) is saved there after each epoch (and every
    :data:`CHECKPOINT_STEPS` steps), and a
    saved state is gone on from: a fit killed and started again ends with the weights of one
    never stopped.

    Returns:
        ``{"losses": [mean loss per step], "steps": int, "train_s": wall seconds}``.
    """
    from tqdm import tqdm

    if not frames:
        raise ValueError("no training frame")
    if settings.hflip and any(f.mirror is None for f in frames):
        raise ValueError("TrainSettings.hflip needs a mirror (CachedFrame.mirror) for every training frame")
    torch.manual_seed(settings.seed)
    order = torch.Generator().manual_seed(settings.seed)
    per_epoch = math.ceil(len(frames) / settings.batch_size)
    total = settings.max_steps or settings.epochs * per_epoch
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=settings.lr, weight_decay=settings.weight_decay)
    model.train()
    losses: list[float] = []
    t0, start = time.perf_counter(), 0
    state = checkpoint.load() if checkpoint is not None else None
    if state is not None:  # a killed fit's last finished epoch
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        order.set_state(state["order"])
        torch.set_rng_state(state["rng"])
        start, losses = int(state["step"]), list(state["losses"])
    perm: list[int] = list(state["perm"]) if state is not None else []
    bar = tqdm(range(start, total), desc="train heads", unit="step", disable=not progress, initial=start, total=total)
    for step in bar:
        if step % per_epoch == 0:
            perm = torch.randperm(len(frames), generator=order).tolist()
        pos = (step % per_epoch) * settings.batch_size
        for group in optimizer.param_groups:
            group["lr"] = _lr(step, total, settings)
        batch = [frames[i] for i in perm[pos:pos + settings.batch_size]]
        if settings.hflip:
            flips = torch.rand(len(batch), generator=order) < 0.5
            batch = [cast(CachedFrame, f.mirror) if flip else f for f, flip in zip(batch, flips.tolist())]
        losses.append(_step(model, batch, optimizer))
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        if checkpoint is not None and ((step + 1) % per_epoch == 0 or (step + 1) % CHECKPOINT_STEPS == 0
                                       or step + 1 == total):
            checkpoint.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                             "order": order.get_state(), "rng": torch.get_rng_state(), "step": step + 1,
                             "losses": losses, "perm": perm})
    model.eval()
    return {"losses": losses, "steps": total, "train_s": time.perf_counter() - t0}


@torch.no_grad()
def detect(model: nn.Module, frames: Sequence[CachedFrame], progress: bool = True,
           passes: int = 1) -> list[dict[str, Tensor]]:
    """Detections of every frame (``boxes [D, 4]`` input pixels, ``labels [D]`` 1..C,
    ``scores [D]``), the model in evaluation mode, the box head run ``passes`` times
    (:func:`frame_forward`)."""
    from tqdm import tqdm

    model.eval()
    return [frame_forward(model, f, passes=passes)
            for f in tqdm(frames, desc="detect", unit="img", disable=not progress)]
