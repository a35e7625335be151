"""Precomputed REEB proposals: compute once per data set, read back every epoch.

REEB has no parameters, so a detector's proposals for a given image never change during
training; :func:`build_cache` computes them once and :class:`ReebRPN(cache=...)
<reeb_torch.detection.ReebRPN>` reads them instead of running the generator.

File format (version 1)
-----------------------
One file written with :func:`torch.save` and read with ``torch.load(weights_only=True)``
(plain containers and tensors only, no pickled classes)::

    {
      "format": "reeb-proposal-cache",
      "version": 1,
      "reeb_version": "0.1.0",             # reeb_torch.__version__ that computed it
      "fingerprint": "3f2a...",            # ReebConfig.fingerprint() of the generator
      "config": {...},                     # ReebConfig.to_dict(), for reading by eye
      "entries": {
        "<image_id>": {
          "digest": "<sha1 hex>",          # image_digest() of the image it was computed on
          "size": [H, W],                  # input image size, pixels
          "path": "<file or ''>",          # where the image came from (information only)
          "boxes": float32 Tensor[N, 4],   # (x1, y1, x2, y2), input pixels, best first
          "scores": float32 Tensor[N],
        },
        ...
      },
    }

Staleness
---------
A cache is *stale* when it was built with another :class:`~reeb_torch.ReebConfig`
(fingerprint), by another version of reeb-torch, or for an image whose content has
since changed. None of these is used silently: loading a cache for another config or
version raises :class:`StaleCacheError`, and proposals are looked up by the *content* of
the image (:func:`image_digest`), so a modified or unknown image raises
:class:`StaleCacheError` too (or is recomputed, with ``ReebRPN(on_miss="compute")``).
:func:`build_cache` on an existing file keeps the entries that are still valid and
recomputes the others.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import torch
from torch import Tensor
from tqdm import tqdm

from .. import __version__
from ..config import ReebConfig
from ..generator import ProposalGenerator

__all__ = [
    "CACHE_FORMAT",
    "CACHE_VERSION",
    "StaleCacheError",
    "CacheEntry",
    "ProposalCache",
    "image_digest",
    "build_cache",
]

CACHE_FORMAT = "reeb-proposal-cache"
CACHE_VERSION = 1


class StaleCacheError(RuntimeError):
    """A proposal cache does not match the config, the library version or an image."""


def _reeb_version() -> str:
    return __version__


def image_digest(image: Tensor) -> str:
    """SHA-1 of an image's 8-bit content and shape, the key proposals are looked up by.

    ``image``: ``3×H×W`` uint8, or float in [0, 1], which is quantised as
    ``round(255 x)`` first, so ``u8`` and ``u8 / 255`` have the same digest. Any device.
    """
    if image.dim() != 3:
        raise ValueError(f"image_digest expects a 3×H×W tensor, got shape {tuple(image.shape)}")
    if image.dtype != torch.uint8:
        if not image.is_floating_point():
            raise ValueError(f"image_digest expects uint8 or float in [0, 1], got {image.dtype}")
        image = (image.detach().float() * 255.0).round_().clamp_(0, 255).to(torch.uint8)
    h = hashlib.sha1()
    h.update(repr(tuple(image.shape)).encode())
    h.update(image.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@dataclass
class CacheEntry:
    """Proposals of one image: ``boxes`` ``Tensor[N, 4]`` and ``scores`` ``Tensor[N]``,
    in pixels of the image of ``size = (H, W)`` whose :func:`image_digest` is ``digest``."""

    digest: str
    size: tuple[int, int]
    boxes: Tensor
    scores: Tensor
    path: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"digest": self.digest, "size": list(self.size), "path": self.path,
                "boxes": self.boxes.float().cpu().contiguous(),
                "scores": self.scores.float().cpu().contiguous()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CacheEntry":
        return cls(digest=str(d["digest"]), size=(int(d["size"][0]), int(d["size"][1])),
                   boxes=d["boxes"], scores=d["scores"], path=str(d.get("path", "")))


class ProposalCache:
    """REEB proposals of a set of images, computed with one config (see module doc).

    Args:
        config: the generator's settings.
        entries: ``image_id -> CacheEntry``.
        reeb_version: library version that computed the entries (default: this one).
    """

    def __init__(self, config: ReebConfig, entries: Mapping[str, CacheEntry] | None = None,
                 reeb_version: str | None = None) -> None:
        self.config = config
        self.fingerprint = config.fingerprint()
        self.reeb_version = reeb_version or _reeb_version()
        self.entries: dict[str, CacheEntry] = {}
        self._by_digest: dict[str, str] = {}
        for image_id, entry in (entries or {}).items():
            self.add(image_id, entry)

    # -- container ----------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.entries)

    def __contains__(self, image_id: object) -> bool:
        return image_id in self.entries

    def __getitem__(self, image_id: str) -> CacheEntry:
        return self.entries[image_id]

    def has_image(self, image: Tensor) -> bool:
        """Whether an entry holds proposals of an image with this content (any id)."""
        return image_digest(image) in self._by_digest

    def add(self, image_id: str, entry: CacheEntry) -> None:
        old = self.entries.get(image_id)
        if old is not None and self._by_digest.get(old.digest) == image_id:
            del self._by_digest[old.digest]
        self.entries[image_id] = entry
        self._by_digest[entry.digest] = image_id

    # -- checks -------------------------------------------------------------------------
    def check_config(self, config: ReebConfig) -> None:
        """Raise :class:`StaleCacheError` unless the cache was built with ``config`` by
        this version of reeb-torch."""
        if config.fingerprint() != self.fingerprint:
            changed = sorted(k for k, v in config.to_dict().items()
                             if self.config.to_dict().get(k) != v)
            raise StaleCacheError(
                f"proposal cache was built with config {self.fingerprint}, not "
                f"{config.fingerprint()} (fields that differ: {', '.join(changed) or '?'}); "
                "rebuild it with build_cache")
        if self.reeb_version != _reeb_version():
            raise StaleCacheError(
                f"proposal cache was built by reeb-torch {self.reeb_version}, this is "
                f"{_reeb_version()}; rebuild it with build_cache")

    def by_digest(self, digest: str) -> CacheEntry | None:
        """The entry of an image of this :func:`image_digest`, or None."""
        image_id = self._by_digest.get(digest)
        return None if image_id is None else self.entries[image_id]

    def lookup(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """``(boxes, scores)`` cached for an image with this content.

        Raises :class:`StaleCacheError` when no entry has the image's digest (the image is
        new, or changed since the cache was built) or the entry's size differs.
        """
        digest = image_digest(image)
        image_id = self._by_digest.get(digest)
        if image_id is None:
            raise StaleCacheError(
                f"image of size {tuple(image.shape[-2:])} (digest {digest[:12]}) is not in the "
                f"proposal cache of {len(self)} images: a new or modified image; rebuild the "
                "cache or use on_miss='compute'")
        entry = self.entries[image_id]
        if tuple(image.shape[-2:]) != entry.size:
            raise StaleCacheError(f"cached image {image_id!r} has size {entry.size}, "
                                  f"the image has {tuple(image.shape[-2:])}")
        return entry.boxes, entry.scores

    # -- file -----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CACHE_FORMAT,
            "version": CACHE_VERSION,
            "reeb_version": self.reeb_version,
            "fingerprint": self.fingerprint,
            "config": self.config.to_dict(),
            "entries": {k: e.to_dict() for k, e in self.entries.items()},
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the cache (atomically: to a temporary file of this process beside it, then renamed).

        Raises:
            OSError: it cannot be written (a full disk, a folder that cannot be made or
            written); no temporary file is left and the file already there is kept.
        """
        path = Path(path)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # two processes never share one
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(self.to_dict(), tmp)
            os.replace(tmp, path)
        except (OSError, RuntimeError) as e:  # torch.save reports a failed write as a RuntimeError
            tmp.unlink(missing_ok=True)
            raise OSError(f"{path}: cannot write ({_write_error(e)})") from None

    @classmethod
    def load(cls, path: str | os.PathLike, config: ReebConfig | None = None) -> "ProposalCache":
        """Read a cache file; with ``config``, raise :class:`StaleCacheError` unless it
        was built with that config by this version (:meth:`check_config`)."""
        try:
            d = torch.load(Path(path), map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise
        except Exception as e:  # noqa: BLE001 - a damaged file: each layer of torch.load raises its own kind
            raise ValueError(f"{path}: not a REEB proposal cache (damaged: {type(e).__name__})") from None
        if not isinstance(d, dict) or d.get("format") != CACHE_FORMAT:
            raise ValueError(f"{path}: not a REEB proposal cache")
        if d.get("version") != CACHE_VERSION:
            raise StaleCacheError(f"{path}: cache format version {d.get('version')}, "
                                  f"this reader knows {CACHE_VERSION}")
        stored = ReebConfig.from_dict(d["config"])
        if stored.fingerprint() != d["fingerprint"]:
            raise StaleCacheError(f"{path}: stored config does not match its fingerprint")
        cache = cls(stored, {k: CacheEntry.from_dict(e) for k, e in d["entries"].items()},
                    reeb_version=str(d["reeb_version"]))
        if config is not None:
            try:
                cache.check_config(config)
            except StaleCacheError as e:
                raise StaleCacheError(f"{path}: {e}") from None
        return cache


def _write_error(e: OSError | RuntimeError) -> str:
    """What a failed cache write says, in a few words: the system's words, or for
    ``torch.save``'s ``RuntimeError`` (its writer's words on a full disk: ``PytorchStreamWriter
    failed writing file ...``, ``unexpected pos ...``) that the write failed."""
    if isinstance(e, OSError):
        return e.strerror or str(e) or type(e).__name__
    return "write failed (the disk may be full)"


def build_cache(
    dataset: Iterable[Mapping[str, Any]],
    path: str | os.PathLike | None = None,
    config: ReebConfig | None = None,
    *,
    generator: torch.nn.Module | None = None,
    device: str | torch.device | None = None,
    progress: bool = True,
) -> ProposalCache:
    """Compute the REEB proposals of every image of ``dataset`` and save them to ``path``.

    Args:
        dataset: items with ``image`` (``3×H×W`` uint8 or float in [0, 1]) and ``image_id``
            (any value; stored as ``str``), optionally ``path``, as
            :class:`reeb_torch.datasets.kitti.KittiDataset` yields.
        path: cache file; when it exists and was built with the same config and version,
            its entries whose image is unchanged are kept and only the rest is computed.
            ``None``: nothing is written.
        config: generator settings (default ``ReebConfig()``).
        generator: module with the :class:`~reeb_torch.ProposalGenerator` contract
            (default ``ProposalGenerator(config)``).
        device: where the generator runs (default: CPU).
        progress: show a tqdm progress bar.

    Returns:
        The :class:`ProposalCache` (also written to ``path``).
    """

    config = config or ReebConfig()
    if generator is None:
        generator = ProposalGenerator(config)
    device = torch.device(device or "cpu")
    generator = generator.to(device)
    cache = ProposalCache(config)
    old: ProposalCache | None = None
    if path is not None and Path(path).exists():
        try:
            old = ProposalCache.load(path, config=config)
        except (StaleCacheError, ValueError):
            old = None  # another config, version or format: recompute everything
    reused = 0
    bar = tqdm(dataset, desc="REEB proposals", unit="img", disable=not progress)
    with torch.no_grad():
        for item in bar:
            image = item["image"]
            image_id = str(item["image_id"])
            digest = image_digest(image)
            entry = old.entries.get(image_id) if old is not None else None
            if entry is None or entry.digest != digest:
                r = generator([image.to(device)])[0]
                entry = CacheEntry(digest=digest, size=(int(image.shape[-2]), int(image.shape[-1])),
                                   boxes=r["boxes"].float().cpu(), scores=r["scores"].float().cpu(),
                                   path=str(item.get("path", "")))
            else:
                reused += 1
            cache.add(image_id, entry)
    if progress and reused:
        bar.write(f"kept {reused} cached entries, computed {len(cache) - reused}")
    if path is not None:
        cache.save(path)
    return cache
