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
frames with KITTI's 2D AP|R40 (moderate; :mod:`reeb_torch.metrics.kitti_ap`) and
frame-bootstrap intervals.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm import tqdm

from .. import __version__
from .._memory import trim_heap
from ..metrics import kitti_ap
from ..ranker import frame_hash
from ..ranker.store import Checkpoints
from .proposal_cache import CacheEntry, ProposalCache, StaleCacheError, image_digest
from .feature_cache import FeatureCache, FrameFeatures, cached_features, frozen_features
from .forward import CachedFrame
from .head_training import TrainSettings, detect, train_heads
from .kitti import distinct_folders, frame_image, load_frames, mirrored

__all__ = ["default_cache_dir", "StoredFrame", "stored_frames", "cached_frames", "fit_detector", "heads_frames", "train_detector", "tune_factorised", "crop_from_labels", "detector_stats", "evaluate_detector", "scores_of",
           "paired_scores", "format_scores", "format_paired"]


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/reeb-torch/detection`` (``~/.cache/...`` without it)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "reeb-torch" / "detection"


def _proposal_cache(det: Any, items: Sequence[dict], root: Path, progress: bool) -> ProposalCache:
    """REEB's proposals of every item, from the cache file of the detector's settings
    (computed and added for the frames it lacks)."""

    rpn = det.model.rpn
    cache, path = _open_proposals(det, root)
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


TRIM_EVERY = 8
"""The per-frame pass hands freed memory back every this many frames (:func:`reeb_torch._memory.trim_heap`)."""

FramesBy = Callable[[Any, Sequence[dict], FeatureCache], Iterator[dict]]
"""The per-frame pass of a fit done elsewhere (:func:`stored_frames`' ``frames_by``)."""


class StoredFrame:
    """A training frame whose image, backbone maps and proposals stay on disk: what a
    :class:`~reeb_torch.detection.forward.CachedFrame` holds, each read when used (the
    maps from the :class:`~reeb_torch.detection.feature_cache.FeatureCache`, the proposals
    from the :class:`~reeb_torch.detection.ProposalCache` by the image's digest, the image
    decoded from its file), so training over many frames holds one step's frames at a time."""

    def __init__(self, item: dict, digest: str, features: FeatureCache | FrameFeatures,
                 proposals: ProposalCache) -> None:
        self.path, self.flipped, self.digest = item["path"], bool(item.get("flipped")), digest
        self.boxes, self.labels = item["boxes"], item["labels"]
        self.ignore, self.dontcare = item["ignore"], item["dontcare"]
        self._features, self._proposals = features, proposals
        self.mirror: StoredFrame | None = None

    @property
    def image(self) -> Tensor:
        """``uint8 [3, H, W]``, decoded from its file."""
        return frame_image({"path": self.path, "flipped": self.flipped})

    @property
    def features(self) -> FrameFeatures:
        f = self._features
        return f if isinstance(f, FrameFeatures) else f.load(self.digest)

    @property
    def proposals(self) -> Tensor:
        """REEB's boxes of the image (input pixels, best first)."""
        entry = self._proposals.by_digest(self.digest)
        if entry is None:
            raise StaleCacheError(f"{self.path}: its proposals are not in the cache")
        return entry.boxes


def _open_proposals(det: Any, root: Path) -> tuple[ProposalCache, Path]:
    """The proposal cache file of the detector's settings under ``root``, as it is (a new
    one where there is none, or a stale one)."""
    rpn = det.model.rpn
    ranker = (det.proposals.get("ranker_sha256") or "none")[:16]
    path = root / "proposals" / f"reeb-{rpn.config.fingerprint()}-{ranker}.pt"
    try:
        return ProposalCache.load(path, config=rpn.config), path
    except (FileNotFoundError, StaleCacheError, ValueError, RuntimeError):
        return ProposalCache(rpn.config), path  # none yet, or stale: start again


def stored_frames(det: Any, items: Sequence[dict], cache_dir: str | os.PathLike | None = None,
                  progress: bool = True, save_every: int = 256, frames_by: FramesBy | None = None) -> list[StoredFrame]:
    """:func:`cached_frames` for lazy items (:func:`~reeb_torch.detection.kitti.load_frames`
    with ``lazy``): one pass decodes each image in turn, computes what the caches lack (REEB's
    proposals, the frozen backbone's maps: the same numbers as :func:`cached_frames`) and
    notes its :func:`~reeb_torch.ranker.frame_hash` (``item["hash"]``); the frames then read
    them from disk when used. The proposals are saved every ``save_every`` new frames, so a
    killed fit keeps what it computed. A cache that cannot be written is one
    ``RuntimeWarning``, and what it would hold is kept in memory.

    ``frames_by(det, items, feature_cache)``: the per-frame work done elsewhere (on Ray:
    :func:`reeb_torch.runs.fit_ray.ray_frames`), an iterator of ``{"digest", "hash", "size",
    "boxes", "scores"}`` per item in order, the maps written to the feature cache."""

    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    rpn = det.model.rpn
    proposals, path = _open_proposals(det, root)
    s = det.settings
    features = FeatureCache(root, det.backbone_sha256, s.min_size, s.max_size, det.precision, s.crop_top)
    precision = getattr(getattr(det.model, "backbone", None), "precision", "float32")
    if precision != features.key["precision"]:
        raise ValueError(f"the model's backbone computes in {precision}, the cache holds "
                         f"{features.key['precision']} maps")
    out: list[StoredFrame] = []
    writable = {"proposals": True}
    feature_writes = [True]
    new = 0

    def save_proposals() -> None:
        if writable["proposals"]:
            try:
                proposals.save(path)
            except OSError as e:
                writable["proposals"] = False
                warnings.warn(f"not caching the proposals: {e}; training goes on without", RuntimeWarning,
                              stacklevel=3)

    computed = frames_by(det, items, features) if frames_by is not None else None
    with torch.no_grad():
        for it in tqdm(items, desc="proposals and backbone maps", unit="img", disable=not progress):
            if computed is not None:
                r = next(computed)
                it["hash"] = r["hash"]
                if proposals.by_digest(r["digest"]) is None:
                    proposals.add(f"{it['folder']}/{it['image_id']}", CacheEntry(
                        r["digest"], tuple(r["size"]), torch.from_numpy(r["boxes"]), torch.from_numpy(r["scores"]),
                        str(it.get("path", ""))))
                    new += 1
                out.append(StoredFrame(it, r["digest"], features, proposals))
                continue
            image = frame_image(it)
            digest = image_digest(image)
            it["hash"] = frame_hash(image)
            if proposals.by_digest(digest) is None:
                r = rpn.generator([image])[0]
                proposals.add(f"{it['folder']}/{it['image_id']}", CacheEntry(
                    digest, (int(image.shape[-2]), int(image.shape[-1])), r["boxes"].float().cpu(),
                    r["scores"].float().cpu(), str(it.get("path", ""))))
                new += 1
                if new % save_every == 0:
                    save_proposals()
            maps, held = cached_features(det.model, image, digest, features, feature_writes)
            out.append(StoredFrame(it, digest, features if held else maps, proposals))
            if len(out) % TRIM_EVERY == 0:
                trim_heap()
    if new % save_every:
        save_proposals()
    rpn.cache, rpn.on_miss = proposals, "compute"
    return out


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
    names = [f"{it['folder']}/{it['image_id']}" for it in items]
    losses = list(history["losses"])[-20:]
    counts = torch.cat([it["labels"] for it in items]).bincount(minlength=len(classes) + 1).tolist()
    return {"folders": [str(f) for f in folders], "frames": names,
            "frame_hashes": {n: it.get("hash") or frame_hash(it["image"]) for n, it in zip(names, items)},
            "objects": {c: int(counts[i + 1]) for i, c in enumerate(classes)},
            "training": {"epochs": training.epochs, "steps": history["steps"], "seed": training.seed,
                         "batch_size": training.batch_size, "lr": training.lr, "hflip": training.hflip,
                         "factorised_epochs": training.factorised_epochs,
                         "final_loss": round(sum(losses) / max(1, len(losses)), 6)},
            "command": command, "reeb_torch": __version__}


def fit_detector(cls: type, folders: Sequence[str | os.PathLike], *, classes: Sequence[str], proposals: str,
                 settings: Any, training: TrainSettings, cache_dir: str | os.PathLike | None = None,
                 limit: int | None = None, auto_crop: bool = False, progress: bool = True,
                 command: str | None = None, checkpoints: str | os.PathLike | None = None,
                 frames_by: FramesBy | None = None, config: Any = None) -> Any:
    """A ``cls`` (:class:`~reeb_torch.detection.ReebDetector`) trained on ``folders`` (module
    doc; a folder named twice is read once), with REEB's ``config`` where given instead of
    ``proposals``' own; ``det.history``: ``{"losses", "steps", "train_s"}``.
    ``auto_crop``: ``settings.crop_top`` from the frames' labels (:func:`crop_from_labels`).
    The frames are read one at a time (:func:`stored_frames`): memory does not grow with
    them. ``checkpoints``: a folder where the training state is kept after each epoch, so the
    same call after a kill goes on from the last finished one (:func:`train_detector`).

    Raises:
        ValueError: a folder without labels, no frame, or no object of ``classes``.
    """
    folders = distinct_folders(folders)[0]  # a folder named twice trains once
    items = load_frames(folders, classes, limit, lazy=True)  # each image decoded in its turn
    if not items:
        raise ValueError(f"no frames in {', '.join(map(str, folders))}")
    if not sum(len(it["boxes"]) for it in items):
        raise ValueError(f"no object of {', '.join(classes)} in {', '.join(map(str, folders))}")
    if auto_crop:
        settings = dataclasses.replace(settings, crop_top=crop_from_labels(items))
    elif settings.crop_top > 0:
        _check_crop(items, settings.crop_top)
    return train_detector(cls, items, folders, classes=classes, proposals=proposals, settings=settings,
                          training=training, cache_dir=cache_dir, progress=progress, command=command,
                          checkpoints=checkpoints, frames_by=frames_by, config=config)


def _check_crop(items: Sequence[dict], crop_top: float) -> None:
    """A ``crop_top`` that skips the rows of every labelled object is refused (the heads
    would learn from nothing); one that skips some of them is a warning."""
    inside = total = 0
    for it in items:
        height = it["size"][0] if "size" in it else it["image"].shape[-2]
        if len(it["boxes"]):
            total += len(it["boxes"])
            inside += int((it["boxes"][:, 3] > crop_top * height).sum())
    if total and not inside:
        raise ValueError(f"crop_top {crop_top:g}: every labelled object lies in the rows the backbone skips (the top "
                         f"{crop_top:g} of each image); lower --crop-top, or use auto")
    if inside < total:
        warnings.warn(f"crop_top {crop_top:g}: {total - inside} of {total} labelled objects lie wholly in the rows the "
                      "backbone skips: the detector cannot learn them", RuntimeWarning, stacklevel=3)


def crop_from_labels(items: Sequence[dict], margin: float = 0.1, step: float = 0.05) -> float:
    """A ``crop_top`` for frames like ``items`` (:func:`~reeb_torch.detection.kitti.load_frames`'
    items): the highest top edge of any of their objects, as a share of its image's height,
    less ``margin``, rounded down to a multiple of ``step`` (0 when an object reaches the
    top ``margin`` of its image, or there is none)."""
    tops = [float(it["boxes"][:, 1].min()) / (it["size"][0] if "size" in it else it["image"].shape[-2])
            for it in items if len(it["boxes"])]
    if not tops:
        return 0.0
    return round(max(0.0, math.floor((min(tops) - margin) / step + 1e-9) * step), 6)


def heads_frames(det: Any, items: Sequence[dict], training: TrainSettings,
                 cache_dir: str | os.PathLike | None = None, progress: bool = True,
                 frames_by: FramesBy | None = None) -> Sequence[Any]:
    """The frames ``det``'s heads train on, for ``items`` (:func:`~reeb_torch.detection.kitti.
    load_frames`' items; lazy ones read one at a time, :func:`stored_frames`): one per item,
    in order, then with ``training.hflip`` their mirror images, each also set as its frame's
    ``mirror``."""
    mirrors = [mirrored(it) for it in items] if training.hflip else []
    lazy = bool(items) and "image" not in items[0]
    frames: Sequence[Any] = (stored_frames(det, [*items, *mirrors], cache_dir, progress, frames_by=frames_by) if lazy
                             else cached_frames(det, [*items, *mirrors], cache_dir, progress))
    for frame, mirror in zip(frames[:len(items)], frames[len(items):]):
        frame.mirror = mirror
    return frames


def train_detector(cls: type, items: Sequence[dict], folders: Sequence[str | os.PathLike], *, classes: Sequence[str],
                   proposals: str, settings: Any, training: TrainSettings, cache_dir: str | os.PathLike | None = None,
                   progress: bool = True, command: str | None = None,
                   checkpoints: str | os.PathLike | None = None, frames_by: FramesBy | None = None,
                   config: Any = None) -> Any:
    """:func:`fit_detector` on frames already read (:func:`~reeb_torch.detection.kitti.
    load_frames`' items, from ``folders``; lazy items are read one at a time). ``checkpoints``:
    the folder of the training's state after each epoch
    (:class:`~reeb_torch.ranker.store.Checkpoints`, keyed by the settings and the frames'
    digests: a state of another fit is not read). ``config``: REEB's settings instead of
    ``proposals``' own (:func:`~reeb_torch.detection.proposal_settings` with ``changes``)."""
    torch.manual_seed(training.seed)  # the heads' initial weights
    rank, int8 = settings.box_head_rank, settings.box_head_int8  # trained in full, made smaller once trained
    det = cls(classes, proposals, dataclasses.replace(settings, box_head_rank=0, box_head_int8=False), config=config)
    if det.precision != settings.precision:  # bfloat16 asked for where it is not native: trained in float32
        det.settings = dataclasses.replace(settings, precision=det.precision)
    frames = heads_frames(det, items, training, cache_dir, progress, frames_by)
    train = frames[:len(items)]
    slot = after = None
    if checkpoints is not None:
        digests = [getattr(f, "digest", None) or image_digest(f.image) for f in frames]
        states = Checkpoints(checkpoints, [dataclasses.asdict(training), repr(det.settings), list(det.classes),
                                           proposals, digests]
                             + ([det.proposals["fingerprint"]] if config is not None else []))
        slot, after = states.slot("heads"), states.slot("factorised")
    try:
        history = train_heads(det.model, train, training, progress=progress, checkpoint=slot)
        if rank:
            tuned = tune_factorised(det, train, rank, training, progress=progress, checkpoint=after)
            if tuned is not None:
                history["factorised"] = tuned
    finally:
        det.model.rpn.cache = None  # new images: REEB runs on them
    if int8:
        det.quantise_box_head()
    det.meta = {"provenance": _provenance(items, folders, training, history, det.classes, command)}
    det.history = history
    return det.eval()


def tune_factorised(det: Any, frames: Sequence[Any], rank: int, training: TrainSettings, *, progress: bool = True,
                    checkpoint: Any = None) -> dict[str, object] | None:
    """Factorise ``det``'s trained box head at ``rank`` (:meth:`ReebDetector.factorise_box_head`)
    and, with ``training.factorised_epochs``, train its heads that many more passes over
    ``frames`` (:meth:`TrainSettings.tuning`), in place. Returns that training's history, or
    ``None`` without it."""
    det.factorise_box_head(rank)
    if not training.factorised_epochs:
        return None
    return train_heads(det.model, frames, training.tuning(), progress=progress, checkpoint=checkpoint)


def detector_stats(det: Any, folders: Sequence[str | os.PathLike], *, limit: int | None = None,
                   cache_dir: str | os.PathLike | None = None, progress: bool = True) -> tuple[list[dict], dict]:
    """``det``'s detections on labelled ``folders``, as KITTI's evaluation counts them.

    Returns:
        ``(items, stats)``: the frames (:func:`~reeb_torch.detection.kitti.load_frames`, in
        order) and :func:`reeb_torch.metrics.kitti_ap.evaluate`'s per-class, per-frame counts
        (moderate), which :func:`~reeb_torch.metrics.kitti_ap.kitti_ap`,
        :func:`~reeb_torch.metrics.kitti_ap.bootstrap` and
        :func:`~reeb_torch.metrics.kitti_ap.paired_bootstrap` take.

    Raises:
        ValueError: a class KITTI's evaluation has no overlap threshold for.
    """

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

    ap = kitti_ap.kitti_ap(stats)
    interval = kitti_ap.bootstrap(stats, samples=samples, seed=seed)
    seen = sum(name is not None for name in det.trained_on([it["image"] for it in items]))
    return {"ap": {k: _pct(v) for k, v in ap.items()},
            "interval_95": {k: [_pct(lo), _pct(hi)] for k, (lo, hi) in interval.items()},
            "objects": {c: sum(s.num_gt for s in stats[c]) for c in det.classes}, "frames": len(items),
            "training_frames": seen}


def paired_scores(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """:func:`~reeb_torch.metrics.kitti_ap.paired_bootstrap`'s result in percent, as JSON takes it:
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
