"""``reeb fit``'s frames and rows: the training rows of the learned ranking
(:mod:`reeb_torch.ranker`) from labelled frames, and the folds of its cross-validation. The
fit itself, on those rows, is :mod:`reeb_torch.ranker.fit`.

* :func:`load_fit_frames` reads KITTI-format folders once: the target objects (car, truck,
  pedestrian, cyclist) and the boxes that are neither target nor background (vans, trams,
  ``DontCare``, ...), whose overlapping candidates teach nothing either way.
* :func:`frame_samples` runs the generator to its candidates (the region cut, eq. 9) and
  keeps each frame's training rows: every candidate at IoU ≥ ``positive_iou`` with a target
  (an object's positives weigh 1 together, so each object counts once) and a seeded sample
  of those below ``negative_iou`` with every labelled box.
* :func:`row_store`: the on-disk store :func:`frame_samples` appends each frame's rows to
  (:class:`~reeb_torch.ranker.store.RowStore`), so that neither the rows nor the images are
  all held at once and a killed fit goes on from the last frame it finished.
* :func:`training_frames`: the frames to fit on when a block is held out, keeping its drive
  neighbours out; the cross-validation itself is :mod:`reeb_torch.ranker.cv`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor
from torchvision.ops import box_iou

from .. import __version__
from .._memory import trim_heap
from ..config import ReebConfig
from ..datasets.folders import folder_names
from ..datasets.kitti import DEFAULT_CLASSES, KittiDataset, read_kitti_labels
from ..io import read_image
from ..ranker import offset_targets, refine_feature_names
from ..ranker.fit import FitOptions, Sample
from ..ranker.store import RowStore, StoredFrames
from ..tuning import FrameCache, Frames, load_frames

__all__ = ["FitFrames", "ImageFiles", "load_fit_frames", "frame_sample", "frame_samples", "mirrored_sample",
           "jitter_of", "row_store", "similar_frames", "training_frames", "drive_of", "other_boxes"]


@dataclass
class FitFrames(Frames):
    """:class:`~reeb_torch.tuning.Frames` with, per frame, ``ignore``: ``float32 [M, 4]``
    the labelled boxes that are no target (other classes, ``DontCare``)."""

    ignore: list[Tensor] = field(default_factory=list)


class ImageFiles(Sequence[Tensor]):
    """Images decoded from their files when asked for (``uint8 [3, H, W]``), so a fit over
    many frames never holds them all: the first ones up to ``budget`` bytes are kept once
    decoded (a fit reads each frame several times), and the last one read."""

    def __init__(self, paths: Sequence[str | os.PathLike], budget: int = 256 << 20) -> None:
        self.paths = [str(p) for p in paths]
        self.budget = budget
        self._kept: dict[int, Tensor] = {}
        self._bytes = 0
        self._last: tuple[int, Tensor] | None = None
        self._reads = 0

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        i = range(len(self))[i]
        if i in self._kept:
            return self._kept[i]
        if self._last is not None and self._last[0] == i:
            return self._last[1]

        image = read_image(self.paths[i])
        self._reads += 1
        if self._reads % 8 == 0:  # a pass over many images of a few sizes fragments the heap: hand it back
            trim_heap()
        size = image.numel() * image.element_size()
        if self._bytes + size <= self.budget:
            self._kept[i] = image
            self._bytes += size
        self._last = (i, image)
        return image

    def stamps(self) -> list[list]:
        """Per image file, ``[path, size, modification time in ns]``: what a store of rows made
        from them is keyed by."""
        out = []
        for p in self.paths:
            st = os.stat(p)
            out.append([p, st.st_size, st.st_mtime_ns])
        return out


def load_fit_frames(roots: Sequence[str | os.PathLike], limit: int | None = None, lazy: bool = False) -> FitFrames:
    """Read the labelled frames of KITTI-format folders (:func:`reeb_torch.tuning.load_frames`)
    and, per frame, the boxes of the other labelled types. ``lazy``: the images are decoded
    when read (:class:`ImageFiles`), not all at once: for frames too many to hold.

    Raises:
        ValueError: as :func:`~reeb_torch.tuning.load_frames`.
    """

    if lazy:
        return _lazy_frames(roots, limit)
    frames = load_frames(roots, limit)
    ignore: list[Tensor] = []
    for root in roots:
        ignore += other_boxes(root, KittiDataset(root, limit=limit).ids)
    return FitFrames(**{f.name: getattr(frames, f.name) for f in dataclasses.fields(Frames)}, ignore=ignore)


def _lazy_frames(roots: Sequence[str | os.PathLike], limit: int | None) -> FitFrames:
    """:func:`load_fit_frames` with the images left in their files: the labels read as
    :func:`~reeb_torch.datasets.folders.load_kitti` reads them (checked against each image's size
    from its header)."""

    if not roots:
        raise ValueError("no data folder given")
    paths: list[str] = []
    gts: list[Tensor] = []
    labels: list[Tensor] = []
    ids: list[str] = []
    folders: list[str] = []
    ignore: list[Tensor] = []
    classes: tuple[str, ...] = tuple(DEFAULT_CLASSES)
    for root, name in zip(roots, folder_names(roots)):
        ds = KittiDataset(root, classes=classes, limit=limit)
        if ds.label_dir is None:
            raise ValueError(f"{root}: no label folder (labels/ or label_2/ beside {ds.image_dir.name}/): "
                             "recall needs the ground-truth boxes")
        for j in range(len(ds)):
            t = ds.load_target(j)
            paths.append(t["path"])
            gts.append(t["boxes"])
            labels.append(t["labels"])
            ids.append(str(t["image_id"]))
            folders.append(name)
        ignore += other_boxes(root, ds.ids)
        classes = tuple(ds.classes)
    if sum(len(g) for g in gts) == 0:
        raise ValueError(f"no labelled object of the classes {', '.join(classes)} in "
                         f"{' '.join(map(str, roots))}: recall is undefined")
    return FitFrames(ImageFiles(paths), gts, labels, classes, ids, folders, ignore=ignore)  # type: ignore[arg-type]


def other_boxes(root: str | os.PathLike, image_ids: Sequence[str]) -> list[Tensor]:
    """Per frame ``image_ids`` of the KITTI-format folder ``root``, ``float32 [M, 4]``: its
    labelled boxes of no target class (vans, trams, ``DontCare``, ...): :attr:`FitFrames.ignore`.

    Raises:
        ValueError: ``root`` has no labels.
    """

    label_dir = KittiDataset(root).label_dir
    if label_dir is None:
        raise ValueError(f"{root}: no label_2 folder: the frames to fit on need labels")
    return [torch.tensor([o.box for o in read_kitti_labels(label_dir / f"{i}.txt") if o.type not in DEFAULT_CLASSES],
                         dtype=torch.float32).reshape(-1, 4) for i in image_ids]


def _labels(boxes: Tensor, gt: Tensor, ignore: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per candidate: best IoU with a target, which target, best IoU with any labelled box."""
    k = len(boxes)
    if len(gt):
        iou = box_iou(boxes, gt)
        best, which = iou.max(1)
    else:
        best, which = torch.zeros(k), torch.full((k,), -1, dtype=torch.long)
    other = box_iou(boxes, ignore).amax(1) if len(ignore) else torch.zeros(k)
    return best, which, torch.maximum(best, other)


def frame_sample(features: Tensor, boxes: Tensor, gt: Tensor, labels: Tensor, ignore: Tensor, opts: FitOptions,
                 rng: np.random.Generator, refine: Callable[[Tensor], Tensor] | None = None) -> Sample:
    """The training rows of one frame's candidates (``features [K, F]``, ``boxes [K, 4]``) for
    its target objects ``gt [N, 4]`` of classes ``labels [N]``; given ``refine`` (boxes
    ``[m, 4]`` to their refiner features ``[m, R]``) and ``opts.refine_hidden``, the refiner's
    rows too: up to ``opts.refine_per_object`` candidates of each object at IoU ≥
    ``opts.refine_iou`` with it (drawn from ``rng`` after the negatives)."""
    best, which, any_iou = _labels(boxes, gt, ignore)
    pos = torch.nonzero(best >= opts.positive_iou).squeeze(1)
    neg = torch.nonzero(any_iou < opts.negative_iou).squeeze(1)
    neg = neg[torch.from_numpy(rng.random(len(neg)) < opts.negatives)]
    per_object = torch.bincount(which[pos], minlength=max(1, len(gt))).float()
    w_pos = 1.0 / per_object[which[pos]]
    near = torch.zeros(0, dtype=torch.long)
    if opts.quality_hidden is not None:  # the quality head's rows below the positives
        near = torch.nonzero((best >= opts.quality_iou[0]) & (best < opts.positive_iou)).squeeze(1)
    idx = torch.cat([pos, neg, near])
    target = torch.cat([torch.ones(len(pos)), torch.zeros(len(neg)), torch.full((len(near),), math.nan)])
    weight = torch.cat([w_pos, torch.ones(len(neg)), torch.zeros(len(near))])
    label = torch.cat([labels[which[pos]], torch.full((len(neg),), -1, dtype=torch.long), labels[which[near]]])
    sample = Sample(features[idx].contiguous(), target, weight, label)
    if opts.quality_hidden is not None:
        mine = (best[idx] >= opts.quality_iou[0]) & (label >= 0)
        count = torch.bincount(which[idx][mine], minlength=max(1, len(gt))).float().clamp(min=1.0)
        sample.iou = best[idx].float()
        sample.object_weight = torch.where(mine, 1.0 / count[which[idx].clamp(min=0)], 0.0)
    if refine is not None and opts.refine_hidden is not None and len(gt):
        near = torch.nonzero(best >= opts.refine_iou).squeeze(1)
        order = torch.from_numpy(rng.permutation(len(near)))
        near = near[order]
        rank = torch.zeros(len(near), dtype=torch.long)  # each candidate's place among its object's draws
        for o in torch.unique(which[near]).tolist():
            at = torch.nonzero(which[near] == o).squeeze(1)
            rank[at] = torch.arange(len(at))
        near = near[rank < opts.refine_per_object].sort().values
        sample.refine_x = refine(boxes[near]).float()
        sample.refine_y = offset_targets(boxes[near], gt[which[near]])
    return sample


def frame_samples(cache: FrameCache, cfg: ReebConfig, opts: FitOptions, indices: Sequence[int] | None = None,
                  progress: Callable | None = None, store: RowStore | None = None) -> list[Sample] | StoredFrames:
    """:func:`frame_sample` of each frame of ``cache`` (``indices``, default all) under ``cfg``;
    frame ``i``'s negatives are drawn by a generator seeded with ``(opts.seed, i)``. With
    ``opts.mirror``, frame ``i``'s sample also holds, after its own rows, those of its mirror
    image (:func:`mirrored_sample`, negatives seeded with ``(opts.seed, i, 1)``); with
    ``opts.jitter``, then those of its jittered copy (:attr:`FitOptions.jitter`).

    ``store`` (:func:`row_store`): each frame's rows are appended to it as they are made
    (the frames it holds already are not made again) and the store's frames are returned:
    memory does not grow with the frames, and a killed fit goes on from the last one."""
    idx = range(len(cache.frames)) if indices is None else indices
    cfg = cfg.unranked()  # the candidates do not depend on the ranker
    out = []
    if store is not None:
        if list(idx) != list(range(len(cache.frames))):
            raise ValueError("frame_samples: a store holds every frame, in order")
        idx = range(len(store), len(cache.frames))
    for i in (progress(idx) if progress else idx):
        parts = [_frame_rows(cache, cfg, opts, i, mirrored=False)]
        if opts.mirror:
            parts.append(_frame_rows(cache, cfg, opts, i, mirrored=True))
        if opts.jitter > 0:
            parts.append(_frame_rows(cache, cfg, opts, i, mirrored=False, photometric=jitter_of(opts, i)))
        sample = (parts[0] if len(parts) == 1 else
                  Sample(*(torch.cat(rows) for rows in zip(*map(dataclasses.astuple, parts)))))
        if store is None:
            out.append(sample)
        else:
            store.append({f.name: getattr(sample, f.name) for f in dataclasses.fields(Sample)})
            if (i + 1) % 8 == 0:  # what the frames freed, handed back: memory stays flat
                trim_heap()
    return out if store is None else store.frames()


STORE_VERSION = 1
"""Bumped whenever the rows :func:`frame_sample` makes change: a store of another version is made again."""


def row_store(folder: str | os.PathLike, cache: FrameCache, cfg: ReebConfig, opts: FitOptions) -> RowStore:
    """The :class:`~reeb_torch.ranker.store.RowStore` in ``folder`` for the training rows of
    ``cache``'s frames under ``cfg`` and ``opts`` (for :func:`frame_samples`): keyed by what
    the rows depend on (the candidates' settings, the options that draw and label the rows,
    the frames' names and image files, the package's version), so a store made otherwise is
    made again, never mixed in.

    Raises:
        StoreError: the folder cannot be written.
    """

    frames = cache.frames
    rows_opts = {k: getattr(opts, k) for k in ("negatives", "positive_iou", "negative_iou", "seed", "mirror",
                                               "jitter", "quality_iou", "refine_iou", "refine_per_object")}
    rows_opts.update(quality=opts.quality_hidden is not None, refine=opts.refine_hidden is not None)
    names = cache.candidates(cfg.unranked(), 0).feature_names
    key = {"config": cfg.unranked().to_dict(), "options": rows_opts, "features": list(names),
           "frames": [f"{f}/{i}" for f, i in zip(frames.folders, frames.ids)],
           "files": getattr(frames.images, "stamps", lambda: None)(), "version": [__version__, STORE_VERSION]}
    fields = {"features": (torch.float32, [len(names)]), "target": (torch.float32, []),
              "weight": (torch.float32, []), "label": (torch.int64, []),
              "refine_x": (torch.float32, [len(refine_feature_names())]), "refine_y": (torch.float32, [4]),
              "iou": (torch.float32, []), "object_weight": (torch.float32, [])}
    return RowStore(folder, key, fields)


def jitter_of(opts: FitOptions, i: int) -> tuple[float, float]:
    """Frame ``i``'s ``(contrast, brightness)`` under ``opts.jitter`` (:attr:`FitOptions.jitter`)."""
    u, v = np.random.default_rng([opts.seed, i, 2]).uniform(-1.0, 1.0, 2)
    return 1.0 + opts.jitter * float(u), 255.0 * opts.jitter * float(v)


def mirrored_sample(cache: FrameCache, cfg: ReebConfig, opts: FitOptions, i: int) -> Sample:
    """The training rows of frame ``i`` of ``cache`` flipped left to right (its image, its
    target and ignored boxes), from the generator's candidates in the flipped image."""
    return _frame_rows(cache, cfg.unranked(), opts, i, mirrored=True)


def _mirror_boxes(boxes: Tensor, width: int) -> Tensor:
    """``[N, 4]`` ``(x1, y1, x2, y2)`` boxes of an image ``width`` pixels wide, as they lie in
    the image flipped left to right: ``(width − x2, y1, width − x1, y2)`` (as the detector's
    training flips them)."""
    return torch.stack([width - boxes[:, 2], boxes[:, 1], width - boxes[:, 0], boxes[:, 3]], 1)


def _frame_rows(cache: FrameCache, cfg: ReebConfig, opts: FitOptions, i: int, mirrored: bool,
                photometric: tuple[float, float] | None = None) -> Sample:
    """:func:`frame_sample` of frame ``i`` (or of its mirror image, or of its copy changed by
    ``photometric``) under the unranked ``cfg``."""
    frames = cache.frames
    c = cache.candidates(cfg, i, mirrored=mirrored, photometric=photometric)
    gt = frames.gts[i]
    ignore = frames.ignore[i] if isinstance(frames, FitFrames) else torch.zeros(0, 4)
    seed = [opts.seed, i]
    if mirrored:
        width = frames.images[i].shape[-1]
        gt, ignore, seed = _mirror_boxes(gt, width), _mirror_boxes(ignore, width), [opts.seed, i, 1]
    elif photometric is not None:
        seed = [opts.seed, i, 3]
    return frame_sample(c.features, c.boxes, gt, frames.labels[i], ignore, opts, np.random.default_rng(seed),
                        lambda b: cache.refine_features(cfg, i, b, mirrored, photometric))


# -- folds ---------------------------------------------------------------------------------------

_DRIVE = re.compile(r"^(.+)_(\d+)$")


def drive_of(image_id: str, folder: str) -> str | None:
    """The drive (sequence) a frame belongs to, from ids of the form ``<drive>_<number>``
    (KITTI tracking: ``t0000_000012``); None for ids that name no drive (KITTI object ids:
    frames drawn from many drives)."""
    m = _DRIVE.match(image_id)
    return f"{folder}/{m.group(1)}" if m else None


def similar_frames(images: Sequence[Tensor], ratio: float = 0.3) -> list[set[int]]:
    """Per frame, the other frames that look nearly the same: the distance between their
    24 × 80 thumbnails is below ``ratio`` times the median distance between all pairs
    (neighbouring frames of one drive, or two moments of one drive among KITTI's object
    frames, whose ids do not name their drive)."""
    thumbs = torch.stack([torch.nn.functional.interpolate(im[None].float(), size=(24, 80), mode="area")[0].flatten()
                          for im in images])
    d = torch.cdist(thumbs, thumbs)
    off = d[~torch.eye(len(images), dtype=torch.bool)]
    limit = ratio * float(off.median()) if off.numel() else 0.0
    return [set(torch.nonzero(d[i] < limit).flatten().tolist()) - {i} for i in range(len(images))]


def training_frames(blocks: list[list[int]], held: int, ids: Sequence[str], folders: Sequence[str],
                    similar: Sequence[set[int]] = (), gap: int = 2) -> list[int]:
    """The frames to fit on when block ``held`` is held out: every other block's frames but
    the frames of the held-out frames' drives within ``gap`` frames of the block (in that
    drive's order) and the frames ``similar`` to a held-out one, so no neighbouring frames of
    one drive fall on both sides."""
    drives = [drive_of(i, f) for i, f in zip(ids, folders)]
    held_set = set(blocks[held])
    near: set[int] = set()
    for d in {drives[i] for i in held_set} - {None}:
        members = [i for i in range(len(ids)) if drives[i] == d]
        pos = [j for j, i in enumerate(members) if i in held_set]
        lo, hi = min(pos) - gap, max(pos) + gap
        near.update(members[j] for j in range(max(0, lo), min(len(members), hi + 1)))
    for i in held_set:
        near.update(similar[i] if similar else ())
    return [i for b, block in enumerate(blocks) if b != held for i in block if i not in near]
