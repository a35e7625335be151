"""Training the detector's heads over cached backbone features, and detecting with them.

With the backbone frozen (:func:`~reeb_torch.detection.reeb_fasterrcnn_lite0`), one step
needs only the cached maps of its frames (:mod:`reeb_torch.detection.feature_cache`). Each
frame goes through :func:`~reeb_torch.detection.forward.frame_forward` (the detector after
its backbone) in training mode, one at a time (a batch's frames differ in size; one at a
time, each frame's maps are exactly those of the frame alone), and a step's gradient is the
mean over its frames; the ignore regions are :func:`~reeb_torch.detection.forward.
drop_ignored`'s.

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import torch
from torch import Tensor, nn
from tqdm import tqdm

from .forward import CachedFrame, frame_forward

__all__ = ["TrainSettings", "mirror_boxes", "train_heads", "detect"]


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


def mirror_boxes(boxes: Tensor, width: int) -> Tensor:
    """``[N, 4]`` ``(x1, y1, x2, y2)`` boxes of an image ``width`` pixels wide, as they lie in
    the image flipped left to right: ``(width − x2, y1, width − x1, y2)``."""
    return torch.stack([width - boxes[:, 2], boxes[:, 1], width - boxes[:, 0], boxes[:, 3]], 1)


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

    model.eval()
    return [frame_forward(model, f, passes=passes)
            for f in tqdm(frames, desc="detect", unit="img", disable=not progress)]
