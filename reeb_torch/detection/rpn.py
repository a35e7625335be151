"""REEB as the proposal stage of a torchvision two-stage detector.

:class:`ReebRPN` keeps the contract of torchvision's
:class:`~torchvision.models.detection.rpn.RegionProposalNetwork`::

    proposals, losses = rpn(images: ImageList, features: dict[str, Tensor], targets=None)

``proposals`` is a list of ``Tensor[N_i, 4]`` ``(x1, y1, x2, y2)`` in the frame of the
transformed (resized, not yet padded) image ``i`` of ``images``, ``0 <= x1 < x2 <= w_i``,
``0 <= y1 < y2 <= h_i`` with ``(h_i, w_i) = images.image_sizes[i]``, best first;
``losses`` is always ``{}`` (REEB has nothing to train). ``features`` and ``targets`` are
not used: in training, :class:`~torchvision.models.detection.roi_heads.RoIHeads` adds the
ground-truth boxes to the proposals itself.

Which image REEB sees
---------------------
A :class:`~torchvision.models.detection.generalized_rcnn.GeneralizedRCNN` hands its RPN
only the normalised, resized and padded batch. REEB is computed from the images *as
they entered the model* instead, and its boxes are mapped to the resized frame with
:func:`torchvision.models.detection.transform.resize_boxes`, the very function (same
ratios ``h_i / H_i``, ``w_i / W_i``, same float32 arithmetic) that maps the ground-truth
boxes. To see those images the RPN must be attached to its model::

    ReebRPN(config).attach(model)   # model.rpn; a forward pre-hook hands it the input images

(:func:`reeb_torch.detection.reeb_fasterrcnn_lite0` does this.) A ``ReebRPN``
that was not attached still works: it recovers the resized image from the batch
(``x * std + mean`` over ``image_sizes[i]``, with the ``image_mean``/``image_std`` it was
given, torchvision's defaults unless told otherwise), computes REEB on it and warns once.

Proposals come from a :class:`~reeb_torch.ProposalGenerator` (run under ``no_grad``) or,
with ``cache=``, from a :class:`~reeb_torch.detection.proposal_cache.ProposalCache` looked up by
the content of each input image (:func:`~reeb_torch.detection.proposal_cache.image_digest`).
"""

from __future__ import annotations

import os
import warnings
from typing import Literal, Sequence

import torch
from torch import Tensor, nn
from torchvision.models.detection.image_list import ImageList
from torchvision.models.detection.transform import resize_boxes
from torchvision.ops import boxes as box_ops

from ..config import ReebConfig
from ..generator import ProposalGenerator
from .proposal_cache import ProposalCache, StaleCacheError

__all__ = ["ReebRPN", "map_boxes"]

# torchvision's detection models normalise with the ImageNet statistics by default.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def map_boxes(
    boxes: Tensor, original_size: Sequence[int], new_size: Sequence[int], min_size: float = 1e-3, top: int = 0
) -> Tensor:
    """Map boxes from an input image to its resized frame, clip them, drop degenerate ones.

    Args:
        boxes: ``Tensor[N, 4]`` ``(x1, y1, x2, y2)`` in pixels of the image of size
            ``original_size = (H, W)``.
        new_size: ``(h, w)`` of the resized image.
        min_size: boxes narrower or lower than this (resized pixels) are dropped.
        top: rows of the resized image cut off above the frame the boxes go to (the
            detector's ``crop_top``): boxes are moved up by ``top`` and clipped to
            ``(h - top, w)``.

    Returns:
        ``Tensor[M, 4]`` float32, ``M <= N``, order kept: ``resize_boxes`` (the function
        torchvision applies to the ground truth), then
        :func:`~torchvision.ops.clip_boxes_to_image` and
        :func:`~torchvision.ops.remove_small_boxes`, as torchvision's RPN does.
    """
    boxes = resize_boxes(boxes.float(), list(original_size), list(new_size))
    if top:
        boxes = boxes - boxes.new_tensor([0.0, top, 0.0, top])
    boxes = box_ops.clip_boxes_to_image(boxes, (int(new_size[0]) - top, int(new_size[1])))
    keep = box_ops.remove_small_boxes(boxes, min_size)
    return boxes[keep]


def _stash_inputs(model: nn.Module, args: tuple, kwargs: dict) -> None:
    """Forward pre-hook of a GeneralizedRCNN: give its RPN the input images."""
    images = args[0] if args else kwargs.get("images")
    rpn = getattr(model, "rpn", None)
    if isinstance(rpn, ReebRPN) and images is not None:
        rpn._inputs = list(images)


class ReebRPN(nn.Module):
    """Training-free region proposals from REEB, in the place of a learned RPN.

    Args:
        config: settings of the generator; ``None`` = :class:`ReebConfig` defaults with
            ``top_k = max(top_k_train, top_k_test)``.
        top_k_train: proposals per image kept in training (torchvision's
            ``rpn_post_nms_top_n_train``; REEB's output is already NMS-ed and ranked).
        top_k_test: proposals per image kept in evaluation.
        cache: a :class:`ProposalCache` (or the path of one) built with ``config``; its
            proposals are used instead of running REEB. A cache built with another
            config raises :class:`StaleCacheError` here.
        on_miss: what to do when an input image is not in the cache (a new or modified
            image): ``"error"`` raises :class:`StaleCacheError`, ``"compute"`` runs REEB.
        min_size: proposals smaller than this, in resized pixels, are dropped.
        image_mean, image_std: the model transform's normalisation, used only when the RPN
            is not attached and has to recover images from the batch.
        generator: the proposal generator to use (any module with the
            :class:`~reeb_torch.ProposalGenerator` contract); a ``ProposalGenerator(config)``
            when ``None``.
    """

    def __init__(
        self,
        config: ReebConfig | None = None,
        *,
        top_k_train: int = 1000,
        top_k_test: int = 300,
        cache: ProposalCache | str | os.PathLike | None = None,
        on_miss: Literal["error", "compute"] = "error",
        min_size: float = 1e-3,
        image_mean: Sequence[float] = IMAGENET_MEAN,
        image_std: Sequence[float] = IMAGENET_STD,
        generator: nn.Module | None = None,
    ) -> None:
        super().__init__()
        for name, n in (("top_k_train", top_k_train),
                        ("top_k_test", top_k_test)):
            if not (isinstance(n, int) and n >= 1):
                raise ValueError(f"ReebRPN.{name} must be an int >= 1, got {n!r}")
        if on_miss not in ("error", "compute"):
            raise ValueError(f"ReebRPN.on_miss must be 'error' or 'compute', got {on_miss!r}")
        if config is None:
            config = ReebConfig().replace(top_k=max(top_k_train, top_k_test))
        self.config = config
        self._top_k = dict(training=top_k_train, testing=top_k_test)
        self.on_miss = on_miss
        self.min_size = min_size
        self.image_mean = tuple(float(v) for v in image_mean)
        self.image_std = tuple(float(v) for v in image_std)
        if isinstance(cache, (str, bytes, os.PathLike)):
            cache = ProposalCache.load(cache, config=config)
        elif cache is not None:
            cache.check_config(config)
        self.cache = cache
        if generator is None:
            generator = ProposalGenerator(config)
        self.generator = generator
        self._inputs: list[Tensor] | None = None
        self._warned = False

    # -- wiring -------------------------------------------------------------------------
    def attach(self, model: nn.Module) -> nn.Module:
        """Make ``model.rpn`` this RPN and let it see ``model``'s input images.

        Registers a forward pre-hook on ``model`` (once) that hands the images given to
        ``model(images, targets)`` to ``model.rpn`` when that is a ``ReebRPN``. The hook is
        a module-level function, so ``copy.deepcopy`` and pickling keep working. Returns
        ``model``.
        """
        model.rpn = self
        if not getattr(model, "_reeb_hooked", False):
            model.register_forward_pre_hook(_stash_inputs, with_kwargs=True)
            setattr(model, "_reeb_hooked", True)  # nn.Module's attributes are typed as tensors and modules
        return model

    def top_k(self) -> int:
        """The proposals per image kept now: ``top_k_train`` in training, else ``top_k_test``."""
        return self._top_k["training" if self.training else "testing"]

    def place(self, boxes: Tensor, original_size: Sequence[int], new_size: Sequence[int], top: int = 0) -> Tensor:
        """The first :meth:`top_k` of an image's ``boxes`` (input pixels, best first)
        in its resized frame (:func:`map_boxes`; ``top``: rows cut above it)."""
        return map_boxes(boxes[:self.top_k()], original_size, new_size, self.min_size, top)

    # -- proposals ----------------------------------------------------------------------
    @torch.no_grad()
    def propose(self, images: list[Tensor]) -> list[Tensor]:
        """REEB boxes for each image, in its own pixels: ``list[Tensor[N_i, 4]]``, best first.

        ``images``: ``3×H×W`` tensors, float in [0, 1] or uint8. Uses the cache when there
        is one (see ``on_miss``), else the generator.
        """
        out: dict[int, Tensor] = {}
        todo: list[int] = []
        for i, image in enumerate(images):
            if self.cache is None:
                todo.append(i)
                continue
            try:
                out[i] = self.cache.lookup(image)[0].to(image.device)
            except StaleCacheError:
                if self.on_miss == "error":
                    raise
                todo.append(i)
        if todo:
            results = self.generator([images[i] for i in todo])
            for i, r in zip(todo, results):
                out[i] = r["boxes"].to(images[i].device)
        return [out[i] for i in range(len(images))]

    def _resized_images(self, images: ImageList) -> list[Tensor]:
        """The resized, un-padded images of the batch in [0, 1] (``x * std + mean``)."""
        t = images.tensors
        mean = torch.tensor(self.image_mean, dtype=t.dtype, device=t.device)[:, None, None]
        std = torch.tensor(self.image_std, dtype=t.dtype, device=t.device)[:, None, None]
        return [
            (t[i, :, :h, :w] * std + mean).clamp_(0.0, 1.0)
            for i, (h, w) in enumerate(images.image_sizes)
        ]

    def forward(
        self,
        images: ImageList,
        features: dict[str, Tensor],
        targets: list[dict[str, Tensor]] | None = None,
    ) -> tuple[list[Tensor], dict[str, Tensor]]:
        """Proposals in the transformed frame of ``images`` and no losses (see module doc)."""
        inputs, self._inputs = self._inputs, None
        if inputs is None or len(inputs) != len(images.image_sizes):
            if not self._warned:
                warnings.warn(
                    "ReebRPN is not attached to its model (call rpn.attach(model)): REEB runs "
                    "on the resized batch recovered with image_mean/image_std, not on the "
                    "input images", stacklevel=2)
                self._warned = True
            inputs = self._resized_images(images)
        boxes = self.propose(inputs)
        proposals = [self.place(b, image.shape[-2:], size).to(images.tensors.dtype)
                     for b, image, size in zip(boxes, inputs, images.image_sizes)]
        return proposals, {}

    def extra_repr(self) -> str:
        cache = f", cache={len(self.cache)} images" if self.cache is not None else ""
        return (f"top_k={self._top_k}, config={self.config.fingerprint()}"
                f"{cache}, on_miss={self.on_miss!r}")
