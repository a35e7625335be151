"""The seeded training loop every part of a ranker's weights is fitted by
(:func:`fit_member`), its losses, and the localisation-quality head's fit
(:func:`quality_rows`, :func:`fit_quality`; ``ReebConfig.rank_quality``, off by default: what
it did held out is in docs/results.md). :func:`reeb_torch.eval.fit.fit_ranker` calls them.
"""

from __future__ import annotations

import math
from typing import Callable, Protocol, Sequence

import torch
from torch import Tensor

from ..ranker import BoxRanker

__all__ = ["Schedule", "fit_member", "logistic_loss", "class_loss", "standardised", "quality_rows", "fit_quality"]


class Schedule(Protocol):
    """What :func:`fit_member` reads of its options (:class:`~reeb_torch.eval.fit.FitOptions` has it)."""

    @property
    def epochs(self) -> int: ...
    @property
    def batch(self) -> int: ...
    @property
    def lr(self) -> float: ...
    @property
    def weight_decay(self) -> float: ...


def logistic_loss(logits: Tensor, y: Tensor, w: Tensor) -> Tensor:
    """The weighted logistic loss of ``logits [n, 1]`` against targets ``y [n]`` in [0, 1]."""
    return torch.nn.functional.binary_cross_entropy_with_logits(logits.squeeze(1), y, weight=w, reduction="sum")


def class_loss(logits: Tensor, y: Tensor, w: Tensor) -> Tensor:
    """The weighted cross-entropy of ``logits [n, C]`` against class indices ``y [n]``."""
    return (torch.nn.functional.cross_entropy(logits, y, reduction="none") * w).sum()


def fit_member(net: torch.nn.Module, x: Tensor, y: Tensor, w: Tensor, opts: Schedule, seed: int,
               loss_fn: Callable[[Tensor, Tensor, Tensor], Tensor] = logistic_loss, fresh: bool = True) -> None:
    """Fit ``net`` on rows ``x`` with targets ``y`` and row weights ``w`` (``loss_fn``: the
    weighted sum over a step's rows, divided by their weight): AdamW, seeded; ``fresh``: from
    seeded initial weights with a one-cycle schedule, else from ``net``'s weights at a
    constant rate (fine-tuning)."""
    gen = torch.Generator().manual_seed(seed)
    if fresh:
        for p in net.parameters():  # the same initial weights for the same seed, whatever ran before
            if p.ndim == 2:
                bound = 1.0 / math.sqrt(p.shape[1])
                p.data.uniform_(-bound, bound, generator=gen)
            else:
                p.data.zero_()
    opt = torch.optim.AdamW(net.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    n = len(x)
    steps = opts.epochs * math.ceil(n / opts.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=opts.lr, total_steps=steps) if fresh else None
    net.train()
    for _ in range(opts.epochs):
        perm = torch.randperm(n, generator=gen)
        for s in range(0, n, opts.batch):
            b = perm[s: s + opts.batch]
            loss = loss_fn(net(x[b]), y[b], w[b])
            opt.zero_grad()
            (loss / w[b].sum()).backward()
            opt.step()
            if sched is not None:
                sched.step()
    net.eval()


def standardised(model: BoxRanker, x: Tensor, dropped: Sequence[int] = ()) -> Tensor:
    """``x`` (``float [n, F]``, the model's columns) as the model's MLPs read it
    (:meth:`~reeb_torch.ranker.BoxRanker.standardise`), the columns ``dropped`` at their mean (0)."""
    xs = model.standardise(x)
    xs[:, list(dropped)] = 0.0
    return xs


def quality_rows(iou: Tensor, object_weight: Tensor, x: Tensor, label: Tensor, grade: tuple[float, float],
                 balance: float) -> tuple[Tensor, Tensor, Tensor] | None:
    """The quality head's rows of ``x`` (``float [n, F]``, the model's columns): those with an
    ``object_weight`` (``float [n]``: 1 / its object's rows at IoU ≥ ``grade[0]``, 0 for the
    others), their targets ``clamp((iou − lo) / (hi − lo), 0, 1)`` (``grade = (lo, hi)``) and
    weights (each object's rows weigh 1 together, each class's objects (objects / the class's
    objects)^``balance`` of ``label``); None without such rows."""
    rows = object_weight > 0
    if not bool(rows.any()):
        return None
    lo, hi = grade
    target = ((iou[rows] - lo) / (hi - lo)).clamp(0.0, 1.0)
    w, lab = object_weight[rows], label[rows]
    if balance:
        per_class = torch.bincount(lab, weights=w)
        factor = torch.where(per_class > 0, (per_class.sum() / per_class.clamp(min=1e-9)) ** balance, 0.0)
        w = w * factor[lab].float()
    return x[rows], target, w


def fit_quality(model: BoxRanker, x: Tensor, target: Tensor, weight: Tensor, opts: Schedule, seed: int,
                hidden: Sequence[int] | None, dropped: Sequence[int] = ()) -> None:
    """Give ``model`` a localisation-quality head with hidden layers ``hidden`` (a model that
    has one, fine-tuned, keeps and tunes its own) fitted on the rows ``x`` (``float [m, F]``,
    the model's columns) to ``target`` (``float [m]`` in [0, 1]: how tight each box is on its
    object) with row weights ``weight``: the logistic loss with soft targets
    (:func:`fit_member`, seeded by ``seed``), on one CPU thread; the columns ``dropped`` held
    at their mean and read by nothing."""
    fresh = model.quality is None
    if fresh:
        assert hidden is not None, "a new quality head needs its widths"
        model.set_quality(hidden)
    assert model.quality is not None
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        xs = standardised(model, x, dropped)
        model.quality.requires_grad_(True)
        fit_member(model.quality, xs, target.float(), weight.float(), opts, seed * 1000 + 996, fresh=fresh)
    finally:
        torch.set_num_threads(threads)
    model.ignore_columns(dropped)
