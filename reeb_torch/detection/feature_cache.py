"""The frozen backbone's feature maps, computed once per frame and kept on disk.

The backbone of :func:`~reeb_torch.detection.reeb_fasterrcnn_lite0` is frozen, so its maps
of a frame never change during training: :func:`frozen_features` computes them once (the
model's transform, then :meth:`Lite0Pyramid.frozen`) and :class:`FeatureCache` files them
as one ``torch.save`` per frame (read with ``weights_only=True``)::

    root/features/lite0-<weights digest[:16]>-<min_size>x<max_size>/<image digest>.pt
    {"format": "reeb-lite0-features", "version": 1,
     "weights": sha256 of the weights file, "min_size": int, "max_size": int,
     "digest": image_digest of the frame, "original_size": [H, W],
     "image_size": [h, w] (resized), "padded_size": [h', w'] (padded to 32),
     "levels": {"0": float16 [40, h'/8, w'/8], "1": float16 [112, h'/16, w'/16],
                "2": float16 [320, h'/32, w'/32]}}

An entry is *stale* when its weights digest, input size settings, image digest or format
differ from what is asked for, or when it cannot be read (a damaged file);
:meth:`FeatureCache.load` refuses it (:class:`~reeb_torch.detection.StaleCacheError`) and
:func:`frozen_features` recomputes and overwrites it. The maps are stored as float16 (about 3 MB per KITTI frame at the default
size) and used as float32.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .cache import StaleCacheError, _write_error, image_digest

__all__ = ["FrameFeatures", "FeatureCache", "compute_features", "frozen_features"]

_FORMAT = "reeb-lite0-features"
_VERSION = 1


@dataclass
class FrameFeatures:
    """The frozen maps of one frame and the sizes that place them.

    Attributes:
        levels: ``{"0", "1", "2"}`` -> ``[C, h'/s, w'/s]`` (float16 on disk).
        original_size: ``(H, W)`` of the input image.
        image_size: ``(h, w)`` after the transform's resize (the frame of the proposals).
        padded_size: ``(h', w')`` of the padded batch the maps were computed on.
    """

    levels: dict[str, Tensor]
    original_size: tuple[int, int]
    image_size: tuple[int, int]
    padded_size: tuple[int, int]


class FeatureCache:
    """Per-frame frozen maps under ``root`` for one weights file and input size.

    Args:
        root: the cache folder (created on first save).
        weights: :func:`~reeb_torch.detection.lite0.weights_digest` of the backbone's weights.
        min_size, max_size: the model transform's resize settings.
    """

    def __init__(self, root: str | os.PathLike, weights: str, min_size: int, max_size: int) -> None:
        self.key = {"format": _FORMAT, "version": _VERSION, "weights": weights,
                    "min_size": int(min_size), "max_size": int(max_size)}
        self.folder = Path(root) / "features" / f"lite0-{weights[:16]}-{min_size}x{max_size}"

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
            return FrameFeatures(levels, _pair(d["original_size"]), _pair(d["image_size"]), _pair(d["padded_size"]))
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
                 "image_size": list(f.image_size), "padded_size": list(f.padded_size),
                 "levels": {k: v.half().contiguous() for k, v in f.levels.items()}}
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            torch.save(entry, tmp)
            os.replace(tmp, self.path(digest))
        except (OSError, RuntimeError) as e:  # torch.save reports a failed write as a RuntimeError
            tmp.unlink(missing_ok=True)
            raise OSError(f"{self.folder}: cannot write ({_write_error(e)})") from None


@torch.no_grad()
def compute_features(model: torch.nn.Module, image: Tensor) -> FrameFeatures:
    """The frozen maps of one ``uint8 [3, H, W]`` (or float in [0, 1]) image: the model's
    transform (resize, normalise, pad to 32) on the image alone, then the frozen backbone,
    exactly as ``model([image])`` computes them."""
    x = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    det: Any = model  # a detector: nn.Module leaves its parts (transform, backbone, ...) untyped
    was_training = det.transform.training
    det.transform.eval()
    try:
        batch, _ = det.transform([x])
    finally:
        det.transform.train(was_training)
    levels = det.backbone.frozen(batch.tensors)
    return FrameFeatures({k: v[0].half() for k, v in levels.items()}, (image.shape[-2], image.shape[-1]),
                         tuple(batch.image_sizes[0]), tuple(batch.tensors.shape[-2:]))


def frozen_features(model: torch.nn.Module, items: Sequence[Mapping[str, Any]], cache: FeatureCache,
                    progress: bool = True) -> list[FrameFeatures]:
    """The frozen maps of every item's ``image``: read from ``cache``, or computed
    (:func:`compute_features`) and saved when missing, stale or damaged; a progress bar. A
    cache that cannot be written (a full disk) is one ``RuntimeWarning``, and the maps are
    kept in memory."""
    from tqdm import tqdm

    out = []
    writable = True
    for it in tqdm(items, desc="backbone features", unit="img", disable=not progress):
        digest = image_digest(it["image"])
        try:
            out.append(cache.load(digest))
            continue
        except (FileNotFoundError, StaleCacheError):
            f = compute_features(model, it["image"])
        if writable:
            try:
                cache.save(digest, f)
                out.append(cache.load(digest))
                continue
            except OSError as e:
                writable = False
                warnings.warn(f"not caching the backbone maps: {e}; training goes on without", RuntimeWarning,
                              stacklevel=2)
        out.append(f)  # float16 maps, as the cache gives them back
    return out


def _pair(v: Any) -> tuple[int, int]:
    h, w = v
    return int(h), int(w)
