"""``reeb fit``'s engine: fit the learned ranking (:mod:`reeb_torch.ranker`) on labelled
frames, and estimate by cross-validation how it does on frames it never saw.

* :func:`load_fit_frames` reads KITTI-format folders once: the target objects (car, truck,
  pedestrian, cyclist) and the boxes that are neither target nor background (vans, trams,
  ``DontCare``, ...), whose overlapping candidates teach nothing either way.
* :func:`frame_samples` runs the generator to its candidates (the region cut, eq. 9) and
  keeps each frame's training rows: every candidate at IoU ≥ ``positive_iou`` with a target
  (an object's positives weigh 1 together, so each object counts once) and a seeded sample
  of those below ``negative_iou`` with every labelled box.
* :func:`fit_ranker` fits a :class:`~reeb_torch.ranker.BoxRanker` (weighted logistic loss,
  AdamW, one CPU thread, seeded: the same frames and options give the same bits:
  :func:`~reeb_torch.eval.training.fit_member`), its localisation-quality head where asked
  (:func:`~reeb_torch.eval.training.fit_quality`), and its box refiner (:func:`fit_refiner`:
  smooth-L1 to the side offsets of the candidates that overlap an object at IoU ≥
  ``refine_iou``, from the same frames' rows).
* :func:`training_frames`: the frames to fit on when a block is held out, keeping its drive
  neighbours out; the cross-validation itself is :mod:`reeb_torch.eval.fit_cv`.
"""

from __future__ import annotations

import copy
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

from ..config import ReebConfig
from ..ranker import (ORIENTATION_NAMES, TARGET_SCALE, BoxRanker, BoxRefiner, dropped_columns, offset_targets,
                      refine_feature_names)
from .training import class_loss, fit_member, fit_quality, quality_rows, standardised
from .tune import FrameCache, Frames

__all__ = ["FitFrames", "FitOptions", "Sample", "load_fit_frames", "frame_sample", "frame_samples", "mirrored_sample",
           "jitter_of", "fit_ranker", "fit_refiner", "initial_model", "similar_frames", "training_frames", "drive_of",
           "other_boxes"]


@dataclass
class FitFrames(Frames):
    """:class:`~reeb_torch.eval.tune.Frames` with, per frame, ``ignore``: ``float32 [M, 4]``
    the labelled boxes that are no target (other classes, ``DontCare``)."""

    ignore: list[Tensor] = field(default_factory=list)


def load_fit_frames(roots: Sequence[str | os.PathLike], limit: int | None = None) -> FitFrames:
    """Read the labelled frames of KITTI-format folders (:func:`reeb_torch.eval.tune.load_frames`)
    and, per frame, the boxes of the other labelled types.

    Raises:
        ValueError: as :func:`~reeb_torch.eval.tune.load_frames`.
    """
    from .data import KittiDataset
    from .tune import load_frames

    frames = load_frames(roots, limit)
    ignore: list[Tensor] = []
    for root in roots:
        ignore += other_boxes(root, KittiDataset(root, limit=limit).ids)
    return FitFrames(**{f.name: getattr(frames, f.name) for f in dataclasses.fields(Frames)}, ignore=ignore)


def other_boxes(root: str | os.PathLike, image_ids: Sequence[str]) -> list[Tensor]:
    """Per frame ``image_ids`` of the KITTI-format folder ``root``, ``float32 [M, 4]``: its
    labelled boxes of no target class (vans, trams, ``DontCare``, ...): :attr:`FitFrames.ignore`.

    Raises:
        ValueError: ``root`` has no labels.
    """
    from .data import DEFAULT_CLASSES, KittiDataset, read_kitti_labels

    label_dir = KittiDataset(root).label_dir
    if label_dir is None:
        raise ValueError(f"{root}: no label_2 folder: the frames to fit on need labels")
    return [torch.tensor([o.box for o in read_kitti_labels(label_dir / f"{i}.txt") if o.type not in DEFAULT_CLASSES],
                         dtype=torch.float32).reshape(-1, 4) for i in image_ids]


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_ranker` fits a model (``reeb fit``'s options).

    Attributes:
        hidden: widths of the MLP's hidden layers.
        members: MLPs fitted from different seeds and averaged.
        prefilter: widths of the prefilter's hidden layers, or None for no prefilter.
        epochs: passes over the training rows.
        negatives: fraction of each frame's negative candidates sampled.
        positive_iou: a candidate at this IoU or more with a target object is a positive.
        negative_iou: a candidate below this IoU with every labelled box is a negative (the
            others are left out).
        balance: each class's objects weigh (all objects / the class's objects)^balance (0:
            every object weighs the same; 1: every class does).
        prefilter_balance: the prefilter's ``balance`` (it decides which candidates the model
            sees), or None: ``balance``.
        lr, weight_decay: AdamW's (a one-cycle schedule peaks at ``lr``).
        batch: rows per step.
        seed: seeds the negatives' sample and the fit.
        class_hidden: widths of the class head's hidden layers (fitted on the positives,
            weighted cross-entropy), or None for no class head.
        class_epochs, class_batch: the class head's passes and rows per step (its rows, the
            positives, are few: ~2400 on the 106 dev frames).
        init: fine-tune this model (a shipped name such as ``"kitti"``, or a weights file)
            instead of fitting one from scratch: its widths, its standardisation and its
            weights are the start, and ``hidden``, ``members``, ``prefilter``,
            ``class_hidden``, ``epochs``, ``lr``, ``batch`` do not apply. For a few labelled
            frames of another camera.
        tune_epochs, tune_lr, tune_batch: the fine-tuning's passes, its constant AdamW
            learning rate (no weight decay: the start, not zero, is what it should stay near)
            and rows per step; the class head is tuned at ``tune_lr`` with its own
            ``class_epochs`` and ``class_batch`` (its rows, the positives, are fewer still).
        mirror: each frame also gives the training rows of its image flipped left to right
            (its boxes flipped with it; the candidates and features the generator finds in the
            flipped image; negatives drawn with a seed of their own). Only the rows a model is
            fitted on: a cross-validation scores its held-out frames as they are.
        jitter: above 0, each frame also gives the training rows of a copy with its contrast
            scaled by 1 + ``jitter``·u and ``jitter``·v·255 grey levels added (u, v uniform
            in [−1, 1], drawn per frame from ``(seed, i, 2)``; its negatives seeded with
            ``(seed, i, 3)``); as ``mirror``, only the rows a model is fitted on.
        refine_hidden: widths of the box refiner's hidden layers
            (:class:`~reeb_torch.ranker.BoxRefiner`, used by ``ReebConfig.refine_top``), or
            None (default) for no refiner (why: docs/results.md, "Box refinement").
        refine_iou: the refiner is fitted on the candidates at this IoU or more with a target.
        refine_per_object: at most this many of them per object (a seeded draw, after the negatives').
        refine_epochs, refine_batch, refine_lr: the refiner's passes, rows per step and peak
            learning rate (AdamW, one-cycle, ``weight_decay``).
        quality_hidden: widths of the localisation-quality head's hidden layers
            (:meth:`~reeb_torch.ranker.BoxRanker.quality_logits`, used by
            ``ReebConfig.rank_quality``), or None (default) for none. Fitted after the ranking
            (which it leaves as it is) on the candidates of objects only.
        quality_iou: ``(lo, hi)``: the quality head's rows are the candidates at IoU ≥ ``lo``
            with a target (each object's weigh 1 together), its target
            ``clamp((IoU − lo) / (hi − lo), 0, 1)`` (a soft target of the logistic loss).
        quality_epochs, quality_batch: the quality head's passes and rows per step (its rows,
            the candidates of the objects, are a small share of the ranking's).
        orientation: the model reads the edge-orientation columns
            (:data:`~reeb_torch.ranker.orientation.ORIENTATION_NAMES`) beside the others; without,
            the generator does not compute them for it (a fine-tuned model reads its own columns).
        hard_negatives: above 0, the ranking's MLP learns from negatives drawn at this
            fraction from the candidates its prefilter keeps in each training frame (the best
            ``ranker_keep``, ``ranker_v_share`` of them by V, as at run time), where it ranks at
            run time, and from the positives among them, in place of the uniform ``negatives``
            sample (a cascade's training; the prefilter, fitted first, and the class head keep
            the uniform rows). Read only where the fit is given the frames
            (:func:`~reeb_torch.eval.fit_cv.kept_rows`: ``reeb fit`` and the cross-validations); 0: off.
        drop_features: feature columns the model does not read (names of
            :func:`~reeb_torch.ranker.features.feature_names`, or a group of
            :data:`~reeb_torch.ranker.features.FEATURE_GROUPS` such as ``"place"``): held at
            their mean in the fit and their input weights set to zero, so the ranking, the
            prefilter and the class head give the same scores whatever those columns hold. The
            weights file's format is the same.
    """

    hidden: tuple[int, ...] = (64, 64)
    members: int = 1
    prefilter: tuple[int, ...] | None = (16,)
    epochs: int = 15
    negatives: float = 0.02
    positive_iou: float = 0.7
    negative_iou: float = 0.5
    balance: float = 0.5
    prefilter_balance: float | None = None
    lr: float = 3e-3
    weight_decay: float = 1e-4
    batch: int = 4096
    seed: int = 0
    class_hidden: tuple[int, ...] | None = (32,)
    class_epochs: int = 60
    class_batch: int = 256
    init: str | None = None
    tune_epochs: int = 10
    tune_lr: float = 1e-3
    tune_batch: int = 1024
    mirror: bool = False
    jitter: float = 0.0
    refine_hidden: tuple[int, ...] | None = None
    refine_iou: float = 0.5
    refine_per_object: int = 100
    refine_epochs: int = 20
    refine_batch: int = 512
    refine_lr: float = 3e-3
    quality_hidden: tuple[int, ...] | None = None
    quality_iou: tuple[float, float] = (0.5, 0.9)
    quality_epochs: int = 30
    quality_batch: int = 256
    orientation: bool = True
    drop_features: tuple[str, ...] = ()
    hard_negatives: float = 0.0


def _no_refine_rows() -> Tensor:
    return torch.zeros(0, len(refine_feature_names()))


@dataclass
class Sample:
    """One frame's training rows: ``features float32 [n, F]``, ``target float32 [n]`` (1 a
    positive, 0 a negative), ``weight float32 [n]`` and ``label int64 [n]`` (the class of a
    positive's object, -1 for a negative); and the box refiner's: ``refine_x float32 [m, R]``
    (:func:`~reeb_torch.ranker.refine_features` of candidates near an object) and
    ``refine_y float32 [m, 4]`` (their side offsets to it, :func:`~reeb_torch.ranker.offset_targets`).
    With :attr:`FitOptions.quality_hidden`, ``iou float32 [n]``, each row's best IoU with a
    target, and ``object_weight float32 [n]``, 1 / the rows of its object at IoU ≥
    ``quality_iou[0]`` (0 for a negative); the rows then also hold the candidates of objects
    below ``positive_iou`` (near misses: ``target`` NaN, weight 0, read by the quality head
    only). Empty otherwise."""

    features: Tensor
    target: Tensor
    weight: Tensor
    label: Tensor
    refine_x: Tensor = field(default_factory=_no_refine_rows)
    refine_y: Tensor = field(default_factory=lambda: torch.zeros(0, 4))
    iou: Tensor = field(default_factory=lambda: torch.zeros(0))
    object_weight: Tensor = field(default_factory=lambda: torch.zeros(0))


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
                  progress: Callable | None = None) -> list[Sample]:
    """:func:`frame_sample` of each frame of ``cache`` (``indices``, default all) under ``cfg``;
    frame ``i``'s negatives are drawn by a generator seeded with ``(opts.seed, i)``. With
    ``opts.mirror``, frame ``i``'s sample also holds, after its own rows, those of its mirror
    image (:func:`mirrored_sample`, negatives seeded with ``(opts.seed, i, 1)``); with
    ``opts.jitter``, then those of its jittered copy (:attr:`FitOptions.jitter`)."""
    idx = range(len(cache.frames)) if indices is None else indices
    cfg = cfg.unranked()  # the candidates do not depend on the ranker
    out = []
    for i in (progress(idx) if progress else idx):
        parts = [_frame_rows(cache, cfg, opts, i, mirrored=False)]
        if opts.mirror:
            parts.append(_frame_rows(cache, cfg, opts, i, mirrored=True))
        if opts.jitter > 0:
            parts.append(_frame_rows(cache, cfg, opts, i, mirrored=False, photometric=jitter_of(opts, i)))
        out.append(parts[0] if len(parts) == 1 else
                   Sample(*(torch.cat(rows) for rows in zip(*map(dataclasses.astuple, parts)))))
    return out


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


def _balanced(w: Tensor, y: Tensor, label: Tensor, balance: float) -> Tensor:
    """The rows' weights ``w`` with each class's objects weighed (objects / the class's
    objects)^``balance``, then the positives' total made the negatives'."""
    if balance:
        per_class = torch.bincount(label[y == 1], weights=w[y == 1])
        factor = torch.where(per_class > 0, (per_class.sum() / per_class.clamp(min=1e-9)) ** balance, 0.0)
        w = torch.where(y == 1, w * factor[label.clamp(min=0)].float(), w)
    return torch.where(y == 1, w * (w[y == 0].sum() / w[y == 1].sum()), w)


def fit_ranker(samples: Sequence[Sample], feature_names: Sequence[str], opts: FitOptions,
               classes: Sequence[str] | None = None,
               hard_rows: Callable[[BoxRanker], Sequence[Sample]] | None = None) -> BoxRanker:
    """A :class:`BoxRanker` fitted on ``samples`` (weighted logistic loss; the positives'
    total weight is made the negatives'), its prefilter on the same rows, and, given the
    ``classes`` the samples' labels index (and ``opts.class_hidden``), a class head on the
    positives (weighted cross-entropy, each class's objects weighed as in the ranking; fitted
    last, so the ranking's weights do not depend on it). Runs on one CPU thread with seeded
    draws, so the same samples and options give the same weights bit for bit.

    With ``opts.init`` it fine-tunes that model instead (:func:`initial_model`): every MLP
    from its weights, on its standardisation, at ``opts.tune_lr`` without weight decay; the
    ranking and the prefilter ``opts.tune_epochs`` passes of ``opts.tune_batch`` rows, the
    class head ``opts.class_epochs`` of ``opts.class_batch`` on the positives of the classes
    it has.

    Raises:
        ValueError: no positive or no negative row (no labelled object found by a candidate).
        RankerWeightsError: ``opts.init`` cannot be read, or reads columns the samples lack.

    ``feature_names`` names the samples' columns; the model reads them all, or all but the
    orientation ones without ``opts.orientation``, or, fine-tuned, its own. ``hard_rows``
    (:func:`~reeb_torch.eval.fit_cv.kept_rows`): with ``opts.hard_negatives`` and a prefilter,
    the MLP is fitted on the rows it gives for the prefilter (fitted first), not on ``samples``.
    """
    names = list(feature_names)
    width = samples[0].features.shape[1] if samples else len(names)
    if width != len(names):
        raise ValueError(f"the samples hold {width} feature columns, feature_names names {len(names)}")
    if opts.init is not None:
        model = initial_model(opts.init, names)
        wanted = list(model.feature_names)
    else:
        wanted = [n for n in names if opts.orientation or n not in ORIENTATION_NAMES]
    x, y, w, label = _stacked(samples, names, wanted)
    q_rows = None  # the quality head's rows, before the near misses leave the rows
    if opts.quality_hidden is not None and len(samples[0].iou):
        q_rows = quality_rows(torch.cat([s.iou for s in samples]), torch.cat([s.object_weight for s in samples]), x,
                              label, opts.quality_iou, opts.balance)
    known = ~torch.isnan(y)  # the near misses are the quality head's rows only
    if not bool(known.all()):
        x, y, w, label = x[known], y[known], w[known], label[known]
    if not bool((y == 1).any()) or not bool((y == 0).any()):
        raise ValueError("no candidate overlaps a labelled object at the positive IoU (or none is background): "
                         "the ranking cannot be fitted on these frames")
    w_object = w  # each object's positives weigh 1 together (the class head's weights)
    w = _balanced(w_object, y, label, opts.balance)
    w_pre = w if opts.prefilter_balance is None else _balanced(w_object, y, label, opts.prefilter_balance)
    if opts.init is not None:
        label = _relabelled(label, classes, model.classes)
        fit = dataclasses.replace(opts, epochs=opts.tune_epochs, lr=opts.tune_lr, batch=opts.tune_batch,
                                  weight_decay=0.0)
        fresh = False
    else:
        heads = classes is not None and opts.class_hidden is not None
        model = BoxRanker(wanted, opts.hidden, opts.members, opts.prefilter,
                          classes if heads else None, opts.class_hidden or ())
        model.mean.copy_(x.mean(0))
        model.scale.copy_(x.std(0).clamp(min=1e-6))
        fit, fresh = opts, True
    dropped = dropped_columns(wanted, opts.drop_features)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        xs = standardised(model, x, dropped)  # the dropped columns at their mean: the fit learns nothing from them
        if model.prefilter is not None:  # first (each part is seeded on its own): hard_rows reads it
            fit_member(model.prefilter, xs[:, : model.cheap], y, w_pre, fit, opts.seed * 1000 + 999, fresh=fresh)
        xm, ym, wm = xs, y, w
        if opts.hard_negatives > 0 and hard_rows is not None and model.prefilter is not None:
            with torch.no_grad():
                xm, ym, wm = _mlp_rows(hard_rows(model), names, wanted, model, opts, dropped)
        for m, member in enumerate(model.members):
            fit_member(member, xm, ym, wm, fit, opts.seed * 1000 + m, fresh=fresh)
        pos = (y == 1) & (label >= 0)
        if model.classifier is not None and bool(pos.any()):
            fit_member(model.classifier, xs[pos], label[pos], w_object[pos],
                        dataclasses.replace(fit, epochs=fit.class_epochs, batch=fit.class_batch),
                        opts.seed * 1000 + 998, class_loss, fresh=fresh)
    finally:
        torch.set_num_threads(threads)
    model.ignore_columns(dropped)  # and read nothing from them when run
    if q_rows is not None:  # fitted after the ranking, which it leaves as it is
        schedule = fit if model.quality is not None else opts  # a fine-tuned model's own head is tuned
        fit_quality(model, *q_rows, dataclasses.replace(schedule, epochs=opts.quality_epochs,
                                                        batch=opts.quality_batch), opts.seed, opts.quality_hidden,
                    dropped)
    rx = torch.cat([s.refine_x for s in samples])
    if opts.refine_hidden is not None and len(rx):  # fitted last: the ranking's weights do not depend on it
        model.refiner = fit_refiner(rx, torch.cat([s.refine_y for s in samples]), opts)
    return model.eval().requires_grad_(False)


def _stacked(samples: Sequence[Sample], names: list[str], wanted: list[str]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The rows of ``samples`` (columns ``names``) together: ``(features, target, weight,
    label)``, the features' columns those ``wanted``."""
    x = torch.cat([s.features for s in samples]).float()
    if wanted != names:  # the columns the model reads, of those the samples hold
        x = x[:, [names.index(n) for n in wanted]]
    return (x, torch.cat([s.target for s in samples]), torch.cat([s.weight for s in samples]),
            torch.cat([s.label for s in samples]))


def _mlp_rows(samples: Sequence[Sample], names: list[str], wanted: list[str], model: BoxRanker, opts: FitOptions,
              dropped: Sequence[int]) -> tuple[Tensor, Tensor, Tensor]:
    """The ranking MLP's rows from :func:`~reeb_torch.eval.fit_cv.kept_rows`' samples:
    ``(xs, y, w)``, standardised as the model's, weighed as :func:`fit_ranker` weighs."""
    x, y, w, label = _stacked(samples, names, wanted)
    if not bool((y == 1).any()) or not bool((y == 0).any()):
        raise ValueError("hard_negatives: the prefilter keeps no positive or no negative in the training frames")
    return standardised(model, x, dropped), y, _balanced(w, y, label, opts.balance)


def fit_refiner(x: Tensor, y: Tensor, opts: FitOptions) -> BoxRefiner:
    """A :class:`~reeb_torch.ranker.BoxRefiner` fitted on the rows ``x`` (``float [m, R]``,
    :func:`~reeb_torch.ranker.refine_features`) to the side offsets ``y`` (``float [m, 4]``):
    smooth-L1 on the offsets over :data:`~reeb_torch.ranker.TARGET_SCALE`, AdamW with a
    one-cycle schedule (``opts.refine_epochs``, ``refine_batch``, ``refine_lr``), seeded by
    ``opts.seed``, on one CPU thread: the same rows and options give the same weights.

    Raises:
        ValueError: no rows, or no ``opts.refine_hidden``.
    """
    if not len(x) or opts.refine_hidden is None:
        raise ValueError("the box refiner needs rows (candidates near an object) and refine_hidden")
    refiner = BoxRefiner(refine_feature_names(), opts.refine_hidden)
    x = x.float()
    refiner.mean.copy_(x.mean(0))
    std = x.std(0) if len(x) > 1 else torch.ones(x.shape[1])
    # a column (nearly) constant on the training rows (a border flag no candidate set) is left
    # unscaled: divided by its tiny spread, a box that sets it would send the offsets anywhere
    refiner.scale.copy_(torch.where(std > 0.01, std, torch.ones_like(std)))
    fit = dataclasses.replace(opts, epochs=opts.refine_epochs, batch=opts.refine_batch, lr=opts.refine_lr)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        xs = (x - refiner.mean) / refiner.scale
        fit_member(refiner.mlp, xs, y.float() / TARGET_SCALE, torch.ones(len(x)), fit, opts.seed * 1000 + 997,
                    _offset_loss)
    finally:
        torch.set_num_threads(threads)
    return refiner.eval().requires_grad_(False)


def _offset_loss(out: Tensor, y: Tensor, w: Tensor) -> Tensor:
    return (torch.nn.functional.smooth_l1_loss(out, y, reduction="none").sum(1) * w).sum()


def initial_model(spec: str, feature_names: Sequence[str]) -> BoxRanker:
    """A trainable copy of the model ``spec`` (a shipped name or a weights file) to fine-tune
    (:attr:`FitOptions.init`), its ``meta`` kept; it reads its own columns, which must be
    among ``feature_names`` (the candidates' columns: with or without the orientation ones).

    Raises:
        RankerWeightsError: as :func:`~reeb_torch.ranker.load_ranker` (missing, damaged), or
            it reads a column ``feature_names`` lacks.
    """
    from ..ranker import RankerWeightsError, load_ranker

    shared = load_ranker(spec)  # shared, read-only: tune a copy
    missing = [n for n in shared.feature_names if n not in feature_names]
    if missing:
        raise RankerWeightsError(f"ranker weights {spec!r} read {len(shared.feature_names)} features (not computed "
                                 f"here: {', '.join(missing[:4])}): fine-tune weights fitted for this config")
    model = copy.deepcopy(shared)
    model.meta = copy.deepcopy(shared.meta)
    return model.requires_grad_(True)


def _relabelled(label: Tensor, classes: Sequence[str] | None, head: Sequence[str] | None) -> Tensor:
    """The positives' labels (indices into ``classes``) as indices into a class head's
    classes ``head``; -1 for a negative, or a class the head lacks (left out of its fit)."""
    if head is None or classes is None:
        return label
    to_head = torch.tensor([head.index(c) if c in head else -1 for c in classes] + [-1])
    return to_head[label]  # label -1 takes the last entry


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
