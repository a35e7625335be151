"""The proposal sources the detection benchmark compares, and their proposals cached per frame.

A source turns one ``uint8 [3, H, W]`` RGB image into ranked boxes
(``{"boxes": float32 [N, 4] (x1, y1, x2, y2) input pixels, best first, "scores": [N]}``):

- ``reeb``: ``reeb_torch.ProposalGenerator()``, the package default at run time (its learned
  ranking with the shipped weights, or the weights ``make_source(..., ranker=PATH)`` names);
- ``training-free``: ``ProposalGenerator(get_preset("training-free"))``, when that preset
  exists (:class:`SourceUnavailable` otherwise);
- ``edgeboxes``, ``selective-search``: :mod:`reeb_torch.eval.baselines` with their
  defaults (OpenCV contrib).

Each source has a ``key`` naming everything its boxes depend on: the REEB config's
fingerprint and the library version, or the baseline's settings and OpenCV's version.
:class:`ProposalStore` files one ``torch.save`` per frame under
``root/proposals/<key>/<image digest>.pt`` and refuses (:class:`StaleCacheError`) an entry
whose stored key, digest or image size differs from what is asked for.
:class:`SourceGenerator` serves the stored boxes with the generator contract, so a
:class:`reeb_torch.detection.ReebRPN` proposes from any source.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import torch
from torch import Tensor, nn

from reeb_torch.detection import StaleCacheError, image_digest

__all__ = [
    "SOURCES",
    "SourceUnavailable",
    "ProposalSource",
    "make_source",
    "ProposalStore",
    "SourceGenerator",
    "cached_proposals",
]

SOURCES = ("reeb", "training-free", "edgeboxes", "selective-search")
"""The training-free sources :func:`make_source` knows."""

_FORMAT = "reeb-detection-proposals"


class SourceUnavailable(RuntimeError):
    """A source that this installation cannot build (e.g. a preset that does not exist yet)."""


@dataclass
class ProposalSource:
    """A named proposal method: ``fn(uint8 [3, H, W]) -> {"boxes", "scores"}`` and the ``key``
    of its settings (a file-name-safe string)."""

    name: str
    key: str
    fn: Callable[[Tensor], Mapping[str, Tensor]]


def _short_hash(text: str) -> str:
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def _reeb_source(name: str, preset: str | None, ranker: str | None = None) -> ProposalSource:
    from reeb_torch import ProposalGenerator, __version__, get_preset

    if preset is not None:
        try:
            config = get_preset(preset)
        except ValueError as e:
            raise SourceUnavailable(f"{name}: no REEB preset {preset!r} in this version ({e})") from None
        gen = ProposalGenerator(config)
    else:
        gen = ProposalGenerator() if ranker is None else ProposalGenerator(ranker=ranker)
    key = f"{name}-{gen.config.fingerprint()}-{_short_hash(__version__)}"
    if gen.config.ranker != "none":  # the same name, other weights: other proposals
        from reeb_torch.ranker import resolve_ranker

        key += "-" + hashlib.sha1(resolve_ranker(gen.config.ranker).read_bytes()).hexdigest()[:16]
    return ProposalSource(name, key, lambda image: gen([image])[0])


def _baseline_source(name: str) -> ProposalSource:
    import cv2

    from reeb_torch.eval.baselines import BASELINES

    baseline = BASELINES[name]()
    settings = repr(sorted(dataclasses.asdict(cast(Any, baseline)).items())) + cv2.__version__
    return ProposalSource(name, f"{name}-{_short_hash(settings)}", baseline)


def make_source(name: str, ranker: str | None = None) -> ProposalSource:
    """Build the source ``name`` (one of :data:`SOURCES`); ``ranker``: the weights the
    ``reeb`` source ranks with (default: the package default's).

    Raises:
        SourceUnavailable: ``training-free`` without that preset.
        ValueError: an unknown name.
    """
    if name == "reeb":
        return _reeb_source(name, None, ranker)
    if name == "training-free":
        return _reeb_source(name, "training-free")
    if name in ("edgeboxes", "selective-search"):
        return _baseline_source(name)
    raise ValueError(f"unknown proposal source {name!r}; known: {', '.join(SOURCES)}")


class ProposalStore:
    """Per-frame proposals of one source on disk (see the module doc)."""

    def __init__(self, root: str | os.PathLike, key: str) -> None:
        self.key = key
        self.folder = Path(root) / "proposals" / key

    def path(self, digest: str) -> Path:
        return self.folder / f"{digest}.pt"

    def load(self, digest: str, size: Sequence[int]) -> tuple[Tensor, Tensor]:
        """``(boxes, scores)`` stored for the image of ``digest`` and ``size = (H, W)``.

        Raises:
            FileNotFoundError: nothing stored; StaleCacheError: an entry for another key,
            image or size.
        """
        d = torch.load(self.path(digest), map_location="cpu", weights_only=True)
        got = (d.get("format"), d.get("key"), d.get("digest"), list(d.get("size", [])))
        want = (_FORMAT, self.key, digest, [int(s) for s in size])
        if got != want:
            raise StaleCacheError(f"{self.path(digest)}: stored for {got[1:]}, asked for {want[1:]}")
        return d["boxes"], d["scores"]

    def save(self, digest: str, size: Sequence[int], boxes: Tensor, scores: Tensor) -> None:
        """Write one entry (atomically: a temporary file, then renamed)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.path(digest).with_suffix(f".{os.getpid()}.tmp")
        torch.save({"format": _FORMAT, "key": self.key, "digest": digest, "size": [int(s) for s in size],
                    "boxes": boxes.float().cpu().contiguous(), "scores": scores.float().cpu().contiguous()}, tmp)
        os.replace(tmp, self.path(digest))


def _as_uint8(image: Tensor) -> Tensor:
    if image.dtype == torch.uint8:
        return image.cpu()
    return (image.detach().float().cpu() * 255.0).round_().clamp_(0, 255).to(torch.uint8)


def _proposals(store: ProposalStore, source: ProposalSource, image: Tensor) -> tuple[Tensor, Tensor]:
    """Stored proposals of ``image``, computed and stored first when missing or stale."""
    digest, size = image_digest(image), tuple(image.shape[-2:])
    try:
        return store.load(digest, size)
    except (FileNotFoundError, StaleCacheError):
        out = source.fn(_as_uint8(image))
        store.save(digest, size, out["boxes"], out["scores"])
        return store.load(digest, size)


def cached_proposals(items: Sequence[Mapping[str, Any]], source: ProposalSource, root: str | os.PathLike,
                     progress: bool = True) -> list[Tensor]:
    """``boxes`` of ``source`` for every item's ``image``, from the store under ``root``
    (computed and stored for the frames it lacks), with a progress bar."""
    from tqdm import tqdm

    store = ProposalStore(root, source.key)
    bar = tqdm(items, desc=f"proposals ({source.name})", unit="img", disable=not progress)
    return [_proposals(store, source, it["image"])[0] for it in bar]


class SourceGenerator(nn.Module):
    """A source's stored proposals behind the :class:`reeb_torch.ProposalGenerator`
    contract: ``forward(images) -> [{"boxes", "scores"}]``, looked up by image content,
    computed and stored on a miss. Hand it to ``ReebRPN(generator=...)``."""

    def __init__(self, source: ProposalSource, root: str | os.PathLike) -> None:
        super().__init__()
        self.source = source
        self.store = ProposalStore(root, source.key)

    @torch.no_grad()
    def forward(self, images: Sequence[Tensor]) -> list[dict[str, Tensor]]:
        out = []
        for image in images:
            boxes, scores = _proposals(self.store, self.source, image)
            out.append({"boxes": boxes.to(image.device), "scores": scores.to(image.device)})
        return out
