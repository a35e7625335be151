"""Detection on new images: REEB's proposals, the frozen backbone per batch, the heads per image.

:func:`detect_images` is what :class:`~reeb_torch.detection.ReebDetector` runs: REEB's
proposals of all images in one call of the generator (it batches images of one size
itself), the backbone once per group of images of one size
(:func:`~reeb_torch.detection.feature_cache.batch_features`: resize, normalise, pad, the
rows above ``crop_top`` cut, the frozen body in its precision), then each image's neck, RoI
pooling, box head and post-processing (:func:`~reeb_torch.detection.forward.
frame_forward`, the very path training's evaluation takes over cached maps).

:class:`StageClock` times each stage (``proposals``, ``resize``, ``backbone``, ``neck``,
``roi_align``, ``box_head``, ``postprocess``) as running totals; on a CUDA device each
stage's end waits for the GPU, so the seconds are the stage's, not its launch's.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from typing import Any

import torch
from torch import Tensor, nn

from .feature_cache import batch_features
from .forward import CachedFrame, frame_forward
from .rpn import ReebRPN

__all__ = ["StageClock", "STAGES", "detect_images"]

STAGES = ("proposals", "resize", "backbone", "neck", "roi_align", "box_head", "postprocess")
"""The stages :class:`StageClock` times, in the order an image meets them."""


class StageClock:
    """Running wall seconds per stage (:data:`STAGES`): ``with clock("backbone"): ...``.

    Args:
        device: where the work runs; on CUDA each stage waits for the GPU before it starts
            and before it ends.
    """

    def __init__(self, device: str | torch.device = "cpu") -> None:
        self.seconds: dict[str, float] = {s: 0.0 for s in STAGES}
        dev = torch.device(device)
        self._sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        self._sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0

    def reset(self) -> None:
        for k in self.seconds:
            self.seconds[k] = 0.0


@torch.no_grad()
def detect_images(model: nn.Module, images: Sequence[Tensor], crop_top: float = 0.0,
                  clock: StageClock | None = None, passes: int = 1) -> list[dict[str, Tensor]]:
    """Detections of each image (``[3, H, W]`` RGB, uint8 or float in [0, 1]; sizes may
    differ; on the model's device): ``boxes`` ``float32 [D, 4]`` input pixels, ``labels``
    ``int64 [D]``, ``scores`` ``float32 [D]``, best first (module doc). The model in
    evaluation mode. ``passes``: the box head's
    (:func:`~reeb_torch.detection.forward.frame_forward`)."""
    stage: Any = clock or (lambda name: nullcontext())
    det: Any = model
    model.eval()
    proposals: list[Tensor | None] = [None] * len(images)
    if isinstance(det.rpn, ReebRPN):
        with stage("proposals"):
            proposals = list(det.rpn.propose(list(images)))
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, image in enumerate(images):
        groups.setdefault(tuple(image.shape), []).append(i)
    out: list[dict[str, Tensor]] = [{} for _ in images]
    empty = torch.zeros(0, 4)
    together = next(model.parameters()).device.type == "cuda"
    chunks = [m for g in groups.values() for m in ([g] if together else [[i] for i in g])]
    for members in chunks:
        feats = batch_features(model, [images[i] for i in members], crop_top, clock=clock)
        for i, f in zip(members, feats):
            frame = CachedFrame(images[i], f, empty, torch.zeros(0, dtype=torch.int64))
            out[i] = frame_forward(model, frame, proposals[i], clock=clock, passes=passes)
    return out
