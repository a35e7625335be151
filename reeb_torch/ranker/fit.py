"""Fitting the learned ranking's weights (:class:`~reeb_torch.ranker.BoxRanker`) on training
rows: :func:`fit_ranker` (the ranking, its prefilter, its class head, the quality head and the
box refiner where asked), :func:`fit_refiner`, :func:`initial_model` (a model to fine-tune),
with :class:`FitOptions` and the rows' :class:`Sample`.

The rows come in memory (a list of :class:`Sample`) or from an on-disk
:class:`~reeb_torch.ranker.store.RowStore` read by minibatch (the same weights bit for bit);
making them from labelled frames (the generator's candidates) is
:mod:`reeb_torch.ranker.frames`'s. Each part is fitted by
:func:`~reeb_torch.ranker.training.fit_member` on one CPU thread with seeded draws: the same
rows and options give the same weights, and a fit killed between epochs goes on from its
checkpoints to the same weights.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor

from .features import dropped_columns
from .model import BoxRanker
from .orientation import ORIENTATION_NAMES
from .refine import TARGET_SCALE, BoxRefiner, refine_feature_names
from .store import RowView, StoredFrames
from .training import Checkpoint, Standardised, class_loss, fit_member, fit_quality, quality_rows, standardised
from .weights import RankerWeightsError, load_ranker

__all__ = ["FitOptions", "Sample", "fit_ranker", "fit_refiner", "initial_model"]


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
            (:func:`~reeb_torch.ranker.cv.kept_rows`: ``reeb fit`` and the cross-validations); 0: off.
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


def _balanced(w: Tensor, y: Tensor, label: Tensor, balance: float) -> Tensor:
    """The rows' weights ``w`` with each class's objects weighed (objects / the class's
    objects)^``balance``, then the positives' total made the negatives'."""
    if balance:
        per_class = torch.bincount(label[y == 1], weights=w[y == 1])
        factor = torch.where(per_class > 0, (per_class.sum() / per_class.clamp(min=1e-9)) ** balance, 0.0)
        w = torch.where(y == 1, w * factor[label.clamp(min=0)].float(), w)
    return torch.where(y == 1, w * (w[y == 0].sum() / w[y == 1].sum()), w)


def fit_ranker(samples: Sequence[Sample] | StoredFrames, feature_names: Sequence[str], opts: FitOptions,
               classes: Sequence[str] | None = None,
               hard_rows: Callable[[BoxRanker], Sequence[Sample]] | None = None,
               checkpoints: Callable[[str], Checkpoint] | None = None) -> BoxRanker:
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
    (:func:`~reeb_torch.ranker.cv.kept_rows`): with ``opts.hard_negatives`` and a prefilter,
    the MLP is fitted on the rows it gives for the prefilter (fitted first), not on ``samples``.

    ``samples`` may be frames of a :class:`~reeb_torch.ranker.store.RowStore`
    (:func:`frame_samples` with a store): the rows are then read by minibatch from its memory
    maps, never all held at once, with the same weights as from the same rows in memory.
    ``checkpoints(part)``: where each part's training state is kept after each epoch
    (:func:`~reeb_torch.ranker.training.fit_member`), to go on from after a kill.
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
    if opts.quality_hidden is not None and len(samples) and len(samples[0].iou):
        q_rows = quality_rows(_field(samples, "iou"), _field(samples, "object_weight"), x,
                              label, opts.quality_iou, opts.balance)
    known = ~torch.isnan(y)  # the near misses are the quality head's rows only
    if not bool(known.all()):
        x = x[known] if isinstance(x, Tensor) else x.subset(known.nonzero().flatten())
        y, w, label = y[known], w[known], label[known]
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
        mean, std = (x.mean(0), x.std(0)) if isinstance(x, Tensor) else x.moments()
        model.mean.copy_(mean)
        model.scale.copy_(std.clamp(min=1e-6))
        fit, fresh = opts, True
    dropped = dropped_columns(wanted, opts.drop_features)
    hard = (lambda m: _mlp_rows(hard_rows(m), names, wanted, m, opts, dropped)) if hard_rows is not None else None
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _fit_parts(model, x, (y, w, w_pre, w_object, label), opts, fit, fresh, dropped, hard,
                   checkpoints or (lambda part: None))
    finally:
        torch.set_num_threads(threads)
    model.ignore_columns(dropped)  # and read nothing from them when run
    if q_rows is not None:  # fitted after the ranking, which it leaves as it is
        schedule = fit if model.quality is not None else opts  # a fine-tuned model's own head is tuned
        fit_quality(model, *q_rows, dataclasses.replace(schedule, epochs=opts.quality_epochs,
                                                        batch=opts.quality_batch), opts.seed, opts.quality_hidden,
                    dropped)
    rx = _field(samples, "refine_x") if opts.refine_hidden is not None else torch.zeros(0)
    if opts.refine_hidden is not None and len(rx):  # fitted last: the ranking's weights do not depend on it
        model.refiner = fit_refiner(rx, _field(samples, "refine_y"), opts)
    return model.eval().requires_grad_(False)


def _fit_parts(model: BoxRanker, x: Tensor | RowView, rows: tuple[Tensor, Tensor, Tensor, Tensor, Tensor],
               opts: FitOptions, fit: FitOptions, fresh: bool, dropped: Sequence[int],
               hard: Callable[[BoxRanker], tuple[Tensor, Tensor, Tensor]] | None,
               slot: Callable[[str], Checkpoint | None]) -> None:
    """:func:`fit_ranker`'s parts in turn, each seeded on its own: the prefilter (first:
    ``hard``, the hard negatives' rows, reads it), the ranking's members, the class head.
    ``rows``: ``(target, weight, prefilter weight, object weight, label)`` of ``x``'s rows."""
    y, w, w_pre, w_object, label = rows
    # the dropped columns at their mean: the fit learns nothing from them
    xs: Tensor | Standardised
    pre: Tensor | Standardised
    if isinstance(x, Tensor):
        xs = standardised(model, x, dropped)
        pre = xs[:, : model.cheap]
    else:
        xs, pre = Standardised(x, model, dropped), Standardised(x, model, dropped, model.cheap)
    if model.prefilter is not None:
        fit_member(model.prefilter, pre, y, w_pre, fit, opts.seed * 1000 + 999, fresh=fresh,
                   checkpoint=slot("prefilter"))
    xm, ym, wm = xs, y, w
    if opts.hard_negatives > 0 and hard is not None and model.prefilter is not None:
        with torch.no_grad():
            xm, ym, wm = hard(model)
    for m, member in enumerate(model.members):
        fit_member(member, xm, ym, wm, fit, opts.seed * 1000 + m, fresh=fresh, checkpoint=slot(f"member{m}"))
    pos = (y == 1) & (label >= 0)
    if model.classifier is not None and bool(pos.any()):
        xp = xs[pos] if isinstance(xs, Tensor) else Standardised(xs.source.subset(pos.nonzero().flatten()), model,
                                                                 dropped)
        fit_member(model.classifier, xp, label[pos], w_object[pos],
                   dataclasses.replace(fit, epochs=fit.class_epochs, batch=fit.class_batch),
                   opts.seed * 1000 + 998, class_loss, fresh=fresh, checkpoint=slot("classifier"))


def _field(samples: Sequence[Sample] | StoredFrames, name: str) -> Tensor:
    """Field ``name`` of every sample together, in memory."""
    if isinstance(samples, StoredFrames):
        return samples.gathered(name)
    return torch.cat([getattr(s, name) for s in samples])


def _stacked(samples: Sequence[Sample] | StoredFrames, names: list[str],
             wanted: list[str]) -> tuple[Tensor | RowView, Tensor, Tensor, Tensor]:
    """The rows of ``samples`` (columns ``names``) together: ``(features, target, weight,
    label)``, the features' columns those ``wanted``; from a store, the features a
    :class:`~reeb_torch.ranker.store.RowView` (read by minibatch)."""
    if isinstance(samples, StoredFrames):
        columns = None if wanted == names else [names.index(n) for n in wanted]
        return (samples.view("features", columns), samples.gathered("target"), samples.gathered("weight"),
                samples.gathered("label"))
    x = torch.cat([s.features for s in samples]).float()
    if wanted != names:  # the columns the model reads, of those the samples hold
        x = x[:, [names.index(n) for n in wanted]]
    return (x, torch.cat([s.target for s in samples]), torch.cat([s.weight for s in samples]),
            torch.cat([s.label for s in samples]))


def _mlp_rows(samples: Sequence[Sample], names: list[str], wanted: list[str], model: BoxRanker, opts: FitOptions,
              dropped: Sequence[int]) -> tuple[Tensor, Tensor, Tensor]:
    """The ranking MLP's rows from :func:`~reeb_torch.ranker.cv.kept_rows`' samples:
    ``(xs, y, w)``, standardised as the model's, weighed as :func:`fit_ranker` weighs."""
    x, y, w, label = _stacked(samples, names, wanted)
    assert isinstance(x, Tensor)  # the hard negatives' rows are in memory
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
