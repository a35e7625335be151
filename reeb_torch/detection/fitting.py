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

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from .cache import CacheEntry, ProposalCache, StaleCacheError, image_digest
from .feature_cache import FeatureCache, frozen_features
from .head_training import CachedFrame, TrainSettings, detect, train_heads
from .kitti import distinct_folders, load_frames, mirrored

__all__ = ["default_cache_dir", "cached_frames", "fit_detector", "train_detector", "crop_from_labels", "detector_stats", "evaluate_detector", "scores_of",
           "paired_scores", "format_scores", "format_paired"]


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
        try:
            cache.save(path)
        except OSError as e:
            warnings.warn(f"not caching the proposals: {e}; training goes on without", RuntimeWarning, stacklevel=3)
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
    cache = FeatureCache(root, det.backbone_sha256, s.min_size, s.max_size, det.precision, s.crop_top)
    feats = frozen_features(det.model, items, cache, progress=progress)
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
                 limit: int | None = None, auto_crop: bool = False, progress: bool = True,
                 command: str | None = None) -> Any:
    """A ``cls`` (:class:`~reeb_torch.detection.ReebDetector`) trained on ``folders`` (module
    doc; a folder named twice is read once); ``det.history``: ``{"losses", "steps", "train_s"}``.
    ``auto_crop``: ``settings.crop_top`` from the frames' labels (:func:`crop_from_labels`).

    Raises:
        ValueError: a folder without labels, no frame, or no object of ``classes``.
    """
    folders = distinct_folders(folders)[0]  # a folder named twice trains once
    items = load_frames(folders, classes, limit)
    if not items:
        raise ValueError(f"no frames in {', '.join(map(str, folders))}")
    if not sum(len(it["boxes"]) for it in items):
        raise ValueError(f"no object of {', '.join(classes)} in {', '.join(map(str, folders))}")
    if auto_crop:
        settings = dataclasses.replace(settings, crop_top=crop_from_labels(items))
    return train_detector(cls, items, folders, classes=classes, proposals=proposals, settings=settings,
                          training=training, cache_dir=cache_dir, progress=progress, command=command)


def crop_from_labels(items: Sequence[dict], margin: float = 0.1, step: float = 0.05) -> float:
    """A ``crop_top`` for frames like ``items`` (:func:`~reeb_torch.detection.kitti.load_frames`'
    items): the highest top edge of any of their objects, as a share of its image's height,
    less ``margin``, rounded down to a multiple of ``step`` (0 when an object reaches the
    top ``margin`` of its image, or there is none)."""
    tops = [float(it["boxes"][:, 1].min()) / it["image"].shape[-2] for it in items if len(it["boxes"])]
    if not tops:
        return 0.0
    return round(max(0.0, math.floor((min(tops) - margin) / step + 1e-9) * step), 6)


def train_detector(cls: type, items: Sequence[dict], folders: Sequence[str | os.PathLike], *, classes: Sequence[str],
                   proposals: str, settings: Any, training: TrainSettings, cache_dir: str | os.PathLike | None = None,
                   progress: bool = True, command: str | None = None) -> Any:
    """:func:`fit_detector` on frames already read (:func:`~reeb_torch.detection.kitti.
    load_frames`' items, from ``folders``)."""
    torch.manual_seed(training.seed)  # the heads' initial weights
    det = cls(classes, proposals, settings)
    if det.precision != settings.precision:  # bfloat16 asked for where it is not native: trained in float32
        det.settings = dataclasses.replace(settings, precision=det.precision)
    mirrors = [mirrored(it) for it in items] if training.hflip else []
    frames = cached_frames(det, [*items, *mirrors], cache_dir, progress)
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


def detector_stats(det: Any, folders: Sequence[str | os.PathLike], *, limit: int | None = None,
                   cache_dir: str | os.PathLike | None = None, progress: bool = True) -> tuple[list[dict], dict]:
    """``det``'s detections on labelled ``folders``, as KITTI's evaluation counts them.

    Returns:
        ``(items, stats)``: the frames (:func:`~reeb_torch.detection.kitti.load_frames`, in
        order) and :func:`reeb_torch.eval.kitti_ap.evaluate`'s per-class, per-frame counts
        (moderate), which :func:`~reeb_torch.eval.kitti_ap.kitti_ap`,
        :func:`~reeb_torch.eval.kitti_ap.bootstrap` and
        :func:`~reeb_torch.eval.kitti_ap.paired_bootstrap` take.

    Raises:
        ValueError: a class KITTI's evaluation has no overlap threshold for.
    """
    from ..eval import kitti_ap

    items = load_frames(folders, det.classes, limit)
    try:
        detections = detect(det.model, cached_frames(det, items, cache_dir, progress), progress=progress,
                            passes=det.settings.box_passes)
    finally:
        det.model.rpn.cache = None
    dets = [{**d, "labels": d["labels"] - 1} for d in detections]
    return items, kitti_ap.evaluate([it["objects"] for it in items], dets, det.classes)


def _pct(v: float) -> float | None:
    return None if math.isnan(v) else round(100 * v, 2)


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
    items, stats = detector_stats(det, folders, limit=limit, cache_dir=cache_dir, progress=progress)
    return scores_of(det, items, stats, samples=samples, seed=seed)


def scores_of(det: Any, items: Sequence[dict], stats: dict, samples: int = 1000, seed: int = 0) -> dict[str, Any]:
    """:func:`evaluate_detector`'s result from :func:`detector_stats`' ``(items, stats)``."""
    from ..eval import kitti_ap

    ap = kitti_ap.kitti_ap(stats)
    interval = kitti_ap.bootstrap(stats, samples=samples, seed=seed)
    seen = sum(name is not None for name in det.trained_on([it["image"] for it in items]))
    return {"ap": {k: _pct(v) for k, v in ap.items()},
            "interval_95": {k: [_pct(lo), _pct(hi)] for k, (lo, hi) in interval.items()},
            "objects": {c: sum(s.num_gt for s in stats[c]) for c in det.classes}, "frames": len(items),
            "training_frames": seen}


def paired_scores(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """:func:`~reeb_torch.eval.kitti_ap.paired_bootstrap`'s result in percent, as JSON takes it:
    per key ``{"a", "b", "diff", "a_interval_95", "b_interval_95", "diff_interval_95",
    "share_b_better", "draws", "verdict"}``."""
    def span(t: tuple[float, float]) -> list[float | None]:
        return [_pct(t[0]), _pct(t[1])]

    return {k: {"a": _pct(d.a), "b": _pct(d.b), "diff": _pct(d.diff), "a_interval_95": span(d.a_interval),
                "b_interval_95": span(d.b_interval), "diff_interval_95": span(d.interval),
                "share_b_better": None if math.isnan(d.share_b_better) else round(d.share_b_better, 4),
                "draws": d.draws, "verdict": d.verdict}
            for k, d in result.items()}


def format_paired(result: dict[str, Any], a: str = "A", b: str = "B") -> str:
    """:func:`paired_scores`' result as a table: each arm's AP|R40 % with its 95 % interval,
    B - A with its interval, and the share of draws where B wins."""
    def cell(v: float | None, span: list[float | None]) -> str:
        text = "-" if v is None else f"{v:.1f} [{span[0]:.1f}, {span[1]:.1f}]"
        return f"{text:<21}"

    lines = [f"A = {a}, B = {b}; AP|R40 % [95 % interval]; B - A from the same frames drawn for both",
             f"{'class':<12}{'A':<21}{'B':<21}{'B - A':<21}{'B wins':>7}  verdict"]
    for key, d in result.items():
        share = "-" if d["share_b_better"] is None else f"{d['share_b_better']:.3f}"
        lines.append(f"{key:<12}{cell(d['a'], d['a_interval_95'])}{cell(d['b'], d['b_interval_95'])}"
                     f"{cell(d['diff'], d['diff_interval_95'])}{share:>7}  {d['verdict']}")
    return "\n".join(lines)


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
