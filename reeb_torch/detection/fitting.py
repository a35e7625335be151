"""Training a :class:`~reeb_torch.detection.ReebDetector` on labelled frames, and scoring it.

:func:`fit_detector` reads KITTI-format folders (:func:`~reeb_torch.detection.kitti.
load_frames`), computes each frame's frozen backbone maps and REEB proposals once and keeps
them under a cache folder (default ``~/.cache/reeb-torch/detection``; ``$XDG_CACHE_HOME``
respected)::

    <cache>/features/lite0-<weights digest>-<min>x<max>/<image digest>.pt   (FeatureCache)
    <cache>/proposals/reeb-<config fingerprint>-<ranker digest>.pt          (ProposalCache)

so a second fit on the same frames (another seed, more epochs) skips both, then trains the
neck and box head over the cached maps (:func:`~reeb_torch.detection.train_heads`):
deterministic for a seed. :func:`evaluate_detector` scores a detector on other labelled
frames with KITTI's 2D AP|R40 (moderate; :mod:`reeb_torch.eval.kitti_ap`) and
frame-bootstrap intervals.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from .cache import CacheEntry, ProposalCache, StaleCacheError, image_digest
from .feature_cache import FeatureCache, frozen_features
from .head_training import CachedFrame, TrainSettings, detect, train_heads
from .kitti import load_frames, mirrored

__all__ = ["default_cache_dir", "cached_frames", "fit_detector", "evaluate_detector", "format_scores"]


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/reeb-torch/detection`` (``~/.cache/...`` without it)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "reeb-torch" / "detection"


def _proposal_cache(det: Any, items: Sequence[dict], root: Path, progress: bool) -> ProposalCache:
    """REEB's proposals of every item, from the cache file of the detector's settings
    (computed and added for the frames it lacks)."""
    from tqdm import tqdm

    rpn = det.model.rpn
    ranker = (det.proposals.get("ranker_sha256") or "none")[:16]
    path = root / "proposals" / f"reeb-{rpn.config.fingerprint()}-{ranker}.pt"
    try:
        cache = ProposalCache.load(path, config=rpn.config)
    except (FileNotFoundError, StaleCacheError, ValueError, RuntimeError):
        cache = ProposalCache(rpn.config)  # none yet, or stale: start again
    todo = [it for it in items if not cache.has_image(it["image"])]
    with torch.no_grad():
        for it in tqdm(todo, desc="REEB proposals", unit="img", disable=not progress or not todo):
            r = rpn.generator([it["image"]])[0]
            cache.add(f"{it['folder']}/{it['image_id']}", CacheEntry(
                image_digest(it["image"]), (int(it["image"].shape[-2]), int(it["image"].shape[-1])),
                r["boxes"].float().cpu(), r["scores"].float().cpu(), str(it.get("path", ""))))
    if todo:
        cache.save(path)
    return cache


def cached_frames(det: Any, items: Sequence[dict], cache_dir: str | os.PathLike | None = None,
                  progress: bool = True) -> list[CachedFrame]:
    """The items as the heads see them: their cached maps and targets; the detector's
    :class:`~reeb_torch.detection.ReebRPN` then reads their proposals from the cache (until
    ``det.model.rpn.cache`` is set back to ``None``)."""
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    rpn = det.model.rpn
    rpn.cache, rpn.on_miss = _proposal_cache(det, items, root, progress), "compute"
    s = det.settings
    feats = frozen_features(det.model, items, FeatureCache(root, det.backbone_sha256, s.min_size, s.max_size),
                            progress=progress)
    return [CachedFrame(it["image"], f, it["boxes"], it["labels"], it["ignore"], it["dontcare"])
            for it, f in zip(items, feats)]


def _provenance(items: Sequence[dict], folders: Sequence[str | os.PathLike], training: TrainSettings,
                history: dict, classes: Sequence[str], command: str | None) -> dict[str, Any]:
    from .. import __version__
    from ..ranker import frame_hash

    names = [f"{it['folder']}/{it['image_id']}" for it in items]
    losses = list(history["losses"])[-20:]
    counts = torch.cat([it["labels"] for it in items]).bincount(minlength=len(classes) + 1).tolist()
    return {"folders": [str(f) for f in folders], "frames": names,
            "frame_hashes": {n: frame_hash(it["image"]) for n, it in zip(names, items)},
            "objects": {c: int(counts[i + 1]) for i, c in enumerate(classes)},
            "training": {"epochs": training.epochs, "steps": history["steps"], "seed": training.seed,
                         "batch_size": training.batch_size, "lr": training.lr, "hflip": training.hflip,
                         "final_loss": round(sum(losses) / max(1, len(losses)), 6)},
            "command": command, "reeb_torch": __version__}


def fit_detector(cls: type, folders: Sequence[str | os.PathLike], *, classes: Sequence[str], proposals: str,
                 settings: Any, training: TrainSettings, cache_dir: str | os.PathLike | None = None,
                 limit: int | None = None, progress: bool = True, command: str | None = None) -> Any:
    """A ``cls`` (:class:`~reeb_torch.detection.ReebDetector`) trained on ``folders`` (module
    doc); ``det.history``: ``{"losses", "steps", "train_s"}``.

    Raises:
        ValueError: a folder without labels, no frame, or no object of ``classes``.
    """
    items = load_frames(folders, classes, limit)
    if not items:
        raise ValueError(f"no frames in {', '.join(map(str, folders))}")
    if not sum(len(it["boxes"]) for it in items):
        raise ValueError(f"no object of {', '.join(classes)} in {', '.join(map(str, folders))}")
    torch.manual_seed(training.seed)  # the heads' initial weights
    det = cls(classes, proposals, settings)
    mirrors = [mirrored(it) for it in items] if training.hflip else []
    frames = cached_frames(det, items + mirrors, cache_dir, progress)
    train = frames[:len(items)]
    for frame, mirror in zip(train, frames[len(items):]):
        frame.mirror = mirror
    try:
        history = train_heads(det.model, train, training, progress=progress)
    finally:
        det.model.rpn.cache = None  # new images: REEB runs on them
    det.meta = {"provenance": _provenance(items, folders, training, history, det.classes, command)}
    det.history = history
    return det.eval()


def evaluate_detector(det: Any, folders: Sequence[str | os.PathLike], *, limit: int | None = None,
                      cache_dir: str | os.PathLike | None = None, samples: int = 1000, seed: int = 0,
                      progress: bool = True) -> dict[str, Any]:
    """KITTI's 2D AP|R40 (moderate) of ``det`` on labelled ``folders``, in percent.

    Returns:
        ``{"ap": {class: %, "mAP": %}, "interval_95": {class: [lo, hi]}, "objects": {class:
        moderate objects}, "frames": n, "training_frames": how many of them ``det`` was trained
        on}`` (``None`` for a class without objects).

    Raises:
        ValueError: a class KITTI's evaluation has no overlap threshold for.
    """
    from ..eval import kitti_ap

    items = load_frames(folders, det.classes, limit)
    try:
        detections = detect(det.model, cached_frames(det, items, cache_dir, progress), progress=progress)
    finally:
        det.model.rpn.cache = None
    dets = [{**d, "labels": d["labels"] - 1} for d in detections]
    stats = kitti_ap.evaluate([it["objects"] for it in items], dets, det.classes)
    ap = kitti_ap.kitti_ap(stats)
    interval = kitti_ap.bootstrap(stats, samples=samples, seed=seed)

    def pct(v: float) -> float | None:
        return None if math.isnan(v) else round(100 * v, 2)

    seen = sum(name is not None for name in det.trained_on([it["image"] for it in items]))
    return {"ap": {k: pct(v) for k, v in ap.items()},
            "interval_95": {k: [pct(lo), pct(hi)] for k, (lo, hi) in interval.items()},
            "objects": {c: sum(s.num_gt for s in stats[c]) for c in det.classes}, "frames": len(items),
            "training_frames": seen}


def format_scores(result: dict[str, Any]) -> str:
    """:func:`evaluate_detector`'s result as a small table (AP|R40 % and its interval)."""
    lines = [f"{'class':<12}{'AP|R40 %':>10}  95 % interval   objects"]
    for name, ap in result["ap"].items():
        lo, hi = result["interval_95"][name]
        n = result["objects"].get(name, sum(result["objects"].values()))
        cell = "-" if ap is None else f"{ap:.1f}"
        span = "" if lo is None else f"[{lo:.1f}, {hi:.1f}]"
        lines.append(f"{name:<12}{cell:>10}  {span:<15}{n:>8}")
    return "\n".join(lines)
