"""The frozen backbone's feature maps, computed once per frame and kept on disk.

The backbone of :func:`~reeb_torch.detection.reeb_fasterrcnn_lite0` is frozen, so its maps
of a frame never change during training: :func:`frozen_features` computes them once
(:func:`compute_features`: the model's transform, the rows above ``crop_top`` cut, then
:meth:`Lite0Pyramid.frozen` in its precision) and :class:`FeatureCache` files them as one
``torch.save`` per frame (read with ``weights_only=True``)::

    root/features/lite0-<weights digest[:16]>-<min_size>x<max_size>-<precision>[-top<crop>]/<image digest>.pt
    {"format": "reeb-lite0-features", "version": 2,
     "weights": sha256 of the weights file, "min_size": int, "max_size": int,
     "precision": "float32" | "bfloat16", "crop_top": float,
     "digest": image_digest of the frame, "original_size": [H, W],
     "image_size": [h, w] (resized), "padded_size": [h', w'] (the maps' frame, padded to 32),
     "top": rows of the resized image above the maps (a multiple of 32),
     "levels": {"0": float16 [40, h'/8, w'/8], "1": float16 [112, h'/16, w'/16],
                "2": float16 [320, h'/32, w'/32]}}

An entry is *stale* when its weights digest, input size settings, precision, crop, image
digest or format differ from what is asked for, or when it cannot be read (a damaged file);
:meth:`FeatureCache.load` refuses it (:class:`~reeb_torch.detection.StaleCacheError`) and
:func:`frozen_features` recomputes and overwrites it. The maps are stored as float16 (about 3 MB per KITTI frame at the default
size) and used as float32.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ContextManager

import torch
from torch import Tensor
from tqdm import tqdm

from .proposal_cache import StaleCacheError, _write_error, image_digest

__all__ = ["FrameFeatures", "FeatureCache", "compute_features", "batch_features", "frozen_features", "cached_features",
           "top_rows"]

_FORMAT = "reeb-lite0-features"
_VERSION = 2


@dataclass
class FrameFeatures:
    """The frozen maps of one frame and the sizes that place them.

    Attributes:
        levels: ``{"0", "1", "2"}`` -> ``[C, h'/s, w'/s]`` (float16 on disk).
        original_size: ``(H, W)`` of the input image.
        image_size: ``(h, w)`` after the transform's resize (the frame of the proposals).
        padded_size: ``(h', w')`` of the padded batch the maps were computed on (below
            ``top``).
        top: rows of the resized image above the maps (cut before the backbone:
            :func:`top_rows`); the maps' row 0 is the resized image's row ``top``.
    """

    levels: dict[str, Tensor]
    original_size: tuple[int, int]
    image_size: tuple[int, int]
    padded_size: tuple[int, int]
    top: int = 0


def top_rows(crop_top: float, height: int) -> int:
    """Rows of a resized image of ``height`` rows that the backbone skips for ``crop_top``
    (a fraction of the height): ``crop_top · height`` rounded down to a multiple of 32, so
    every level's cells keep their place."""
    return 32 * math.floor(crop_top * height / 32)


class FeatureCache:
    """Per-frame frozen maps under ``root`` for one weights file and input size.

    Args:
        root: the cache folder (created on first save).
        weights: :func:`~reeb_torch.detection.lite0.weights_digest` of the backbone's weights.
        min_size, max_size: the model transform's resize settings.
        precision: the frozen body's (``"float32"`` or ``"bfloat16"``).
        crop_top: the share of the resized height above the maps (:func:`top_rows`).
    """

    def __init__(self, root: str | os.PathLike, weights: str, min_size: int, max_size: int,
                 precision: str = "float32", crop_top: float = 0.0) -> None:
        self.crop_top = float(crop_top)
        self.key = {"format": _FORMAT, "version": _VERSION, "weights": weights, "min_size": int(min_size),
                    "max_size": int(max_size), "precision": str(precision), "crop_top": self.crop_top}
        crop = f"-top{crop_top:g}" if crop_top else ""
        self.folder = Path(root) / "features" / f"lite0-{weights[:16]}-{min_size}x{max_size}-{precision}{crop}"

    def path(self, digest: str) -> Path:
        return self.folder / f"{digest}.pt"

    def load(self, digest: str) -> FrameFeatures:
        """The entry of the image ``digest``.

        Raises:
            FileNotFoundError: none; StaleCacheError: one made with other weights, sizes,
            format, or for another image, or one that cannot be read (damaged).
        """
        path = self.path(digest)
        try:
            d = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise
        except Exception as e:  # noqa: BLE001 - a damaged file: each layer of torch.load raises its own kind
            raise StaleCacheError(f"{path}: damaged feature cache entry ({type(e).__name__})") from None
        if not isinstance(d, dict):
            raise StaleCacheError(f"{path}: damaged feature cache entry (not a dict)")
        wrong = {k: d.get(k) for k, v in {**self.key, "digest": digest}.items() if d.get(k) != v}
        if wrong:
            raise StaleCacheError(f"{path}: stale feature cache entry ({wrong} differ "
                                  f"from {({k: self.key.get(k, digest) for k in wrong})})")
        try:
            levels = {str(k): v for k, v in d["levels"].items()}
            if not all(isinstance(v, Tensor) and v.dim() == 3 for v in levels.values()):
                raise TypeError("levels")
            return FrameFeatures(levels, _pair(d["original_size"]), _pair(d["image_size"]), _pair(d["padded_size"]),
                                 int(d["top"]))
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise StaleCacheError(f"{path}: damaged feature cache entry ({type(e).__name__}: {e})") from None

    def save(self, digest: str, f: FrameFeatures) -> None:
        """Write one entry (atomically: a temporary file, then renamed).

        Raises:
            OSError: it cannot be written (a full disk, a folder that cannot be made or
            written); no temporary file is left and an entry already there is kept.
        """
        tmp = self.path(digest).with_suffix(f".{os.getpid()}.tmp")  # two processes never share one
        entry = {**self.key, "digest": digest, "original_size": list(f.original_size),
                 "image_size": list(f.image_size), "padded_size": list(f.padded_size), "top": f.top,
                 "levels": {k: v.half().contiguous() for k, v in f.levels.items()}}
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            torch.save(entry, tmp)
            os.replace(tmp, self.path(digest))
        except (OSError, RuntimeError) as e:  # torch.save reports a failed write as a RuntimeError
            tmp.unlink(missing_ok=True)
            raise OSError(f"{self.folder}: cannot write ({_write_error(e)})") from None


def _as_float(image: Tensor) -> Tensor:
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


@torch.no_grad()
def batch_features(model: torch.nn.Module, images: Sequence[Tensor], crop_top: float = 0.0,
                   clock: Callable[[str], ContextManager[Any]] | None = None) -> list[FrameFeatures]:
    """The frozen maps of images of ONE size (``uint8 [3, H, W]``, or float in [0, 1]) in one
    pass of the backbone: the model's transform (resize, normalise, pad to 32), the rows
    above ``crop_top`` cut (:func:`top_rows`), then the frozen body in its precision. The
    maps keep the body's dtype and channels-last layout (views of the batch's). ``clock``
    times the ``resize`` and ``backbone`` stages
    (:class:`~reeb_torch.detection.inference.StageClock`)."""
    if len({tuple(im.shape) for im in images}) > 1:
        raise ValueError("batch_features: the images of one call must have one size")
    stage = clock or (lambda name: nullcontext())
    det: Any = model  # a detector: nn.Module leaves its parts (transform, backbone, ...) untyped
    was_training = det.transform.training
    det.transform.eval()
    try:
        with stage("resize"):
            batch, _ = det.transform([_as_float(im) for im in images])
    finally:
        det.transform.train(was_training)
    top = top_rows(crop_top, batch.image_sizes[0][0])
    x = batch.tensors[:, :, top:]
    with stage("backbone"):
        levels = det.backbone.frozen(x)
    original = (int(images[0].shape[-2]), int(images[0].shape[-1]))
    return [FrameFeatures({k: v[i] for k, v in levels.items()}, original, tuple(batch.image_sizes[i]),
                          tuple(x.shape[-2:]), top) for i in range(len(images))]


def compute_features(model: torch.nn.Module, image: Tensor, crop_top: float = 0.0) -> FrameFeatures:
    """The frozen maps of one ``uint8 [3, H, W]`` (or float in [0, 1]) image
    (:func:`batch_features` of the image alone), float16, as the cache keeps them."""
    f = batch_features(model, [image], crop_top)[0]
    f.levels = {k: v.half().contiguous() for k, v in f.levels.items()}
    return f


def frozen_features(model: torch.nn.Module, items: Sequence[Mapping[str, Any]], cache: FeatureCache,
                    progress: bool = True) -> list[FrameFeatures]:
    """The frozen maps of every item's ``image``: read from ``cache``, or computed
    (:func:`compute_features`) and saved when missing, stale or damaged; a progress bar. A
    cache that cannot be written (a full disk) is one ``RuntimeWarning``, and the maps are
    kept in memory."""

    precision = getattr(getattr(model, "backbone", None), "precision", "float32")
    if precision != cache.key["precision"]:
        raise ValueError(f"the model's backbone computes in {precision}, the cache holds {cache.key['precision']} maps")
    writable = [True]
    return [cached_features(model, it["image"], image_digest(it["image"]), cache, writable)[0]
            for it in tqdm(items, desc="backbone features", unit="img", disable=not progress)]


def cached_features(model: torch.nn.Module, image: Tensor, digest: str, cache: FeatureCache,
                    writable: list[bool]) -> tuple[FrameFeatures, bool]:
    """The frozen maps of ``image`` (its :func:`~reeb_torch.detection.proposal_cache.image_digest`
    ``digest``) from ``cache``, computed (:func:`compute_features`) and saved where they are
    missing, stale or damaged; and whether the cache holds them. ``writable[0]``: whether
    the cache is still written; the first write that fails (a full disk) is one
    ``RuntimeWarning`` and sets it False, and the maps are then given as computed."""
    try:
        return cache.load(digest), True
    except (FileNotFoundError, StaleCacheError):
        f = compute_features(model, image, cache.crop_top)
    if writable[0]:
        try:
            cache.save(digest, f)
            return cache.load(digest), True
        except OSError as e:
            writable[0] = False
            warnings.warn(f"not caching the backbone maps: {e}; training goes on without", RuntimeWarning,
                          stacklevel=3)
    return f, False  # float16 maps, as the cache gives them back


def _pair(v: Any) -> tuple[int, int]:
    h, w = v
    return int(h), int(w)
