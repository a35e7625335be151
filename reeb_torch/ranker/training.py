"""The seeded training loop every part of a ranker's weights is fitted by
(:func:`fit_member`), its losses, and the localisation-quality head's fit
(:func:`quality_rows`, :func:`fit_quality`; ``ReebConfig.rank_quality``, off by default: what
it did held out is in docs/results.md). :func:`reeb_torch.ranker.fit.fit_ranker` calls them.
"""

from __future__ import annotations

import math
from typing import Callable, Protocol, Sequence

import torch
from torch import Tensor

from .model import BoxRanker
from .store import RowView

__all__ = ["Schedule", "Rows", "Standardised", "Checkpoint", "fit_member", "logistic_loss", "class_loss", "standardised", "quality_rows", "fit_quality"]


class Schedule(Protocol):
    """What :func:`fit_member` reads of its options (:class:`~reeb_torch.ranker.fit.FitOptions` has it)."""

    @property
    def epochs(self) -> int: ...
    @property
    def batch(self) -> int: ...
    @property
    def lr(self) -> float: ...
    @property
    def weight_decay(self) -> float: ...


class Rows(Protocol):
    """Training rows read by minibatch (a :class:`~reeb_torch.ranker.store.RowView`, or
    :class:`Standardised` over one): ``len`` rows, ``rows(b)`` those at positions ``b``."""

    def __len__(self) -> int: ...
    def rows(self, b: Tensor) -> Tensor: ...


class Standardised:
    """``source``'s rows (the model's columns) as the model's MLPs read them
    (:func:`standardised`), the first ``width`` columns only where given: computed per
    minibatch, the same numbers as standardising all rows first."""

    def __init__(self, source: RowView, model: BoxRanker, dropped: Sequence[int] = (), width: int | None = None) -> None:
        self.source, self.model, self.dropped, self.width = source, model, list(dropped), width

    def __len__(self) -> int:
        return len(self.source)

    def rows(self, b: Tensor) -> Tensor:
        xs = standardised(self.model, self.source.rows(b), self.dropped)
        return xs if self.width is None else xs[:, : self.width]


class Checkpoint(Protocol):
    """Where :func:`fit_member` keeps its state after each finished epoch, to go on from it
    when a killed fit is started again (:class:`~reeb_torch.ranker.store.Checkpoints`)."""

    def load(self) -> dict | None: ...
    def save(self, state: dict) -> None: ...


def logistic_loss(logits: Tensor, y: Tensor, w: Tensor) -> Tensor:
    """The weighted logistic loss of ``logits [n, 1]`` against targets ``y [n]`` in [0, 1]."""
    return torch.nn.functional.binary_cross_entropy_with_logits(logits.squeeze(1), y, weight=w, reduction="sum")


def class_loss(logits: Tensor, y: Tensor, w: Tensor) -> Tensor:
    """The weighted cross-entropy of ``logits [n, C]`` against class indices ``y [n]``."""
    return (torch.nn.functional.cross_entropy(logits, y, reduction="none") * w).sum()


def fit_member(net: torch.nn.Module, x: Tensor | Rows, y: Tensor, w: Tensor, opts: Schedule, seed: int,
               loss_fn: Callable[[Tensor, Tensor, Tensor], Tensor] = logistic_loss, fresh: bool = True,
               checkpoint: Checkpoint | None = None) -> None:
    """Fit ``net`` on rows ``x`` (a tensor, or :class:`Rows` read by minibatch) with targets
    ``y`` and row weights ``w`` (``loss_fn``: the weighted sum over a step's rows, divided by
    their weight): AdamW, seeded; ``fresh``: from seeded initial weights with a one-cycle
    schedule, else from ``net``'s weights at a constant rate (fine-tuning).

    ``checkpoint``: the state (weights, optimiser, schedule, generator, epoch) is saved there
    after each epoch, and a saved state is gone on from: a fit killed and started again ends
    with the same weights as one never stopped."""
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
    start = 0
    state = checkpoint.load() if checkpoint is not None else None
    if state is not None:
        net.load_state_dict(state["net"])
        opt.load_state_dict(state["opt"])
        if sched is not None:
            sched.load_state_dict(state["sched"])
        gen.set_state(state["gen"])
        start = int(state["epoch"])
    net.train()
    for epoch in range(start, opts.epochs):
        perm = torch.randperm(n, generator=gen)
        for s in range(0, n, opts.batch):
            b = perm[s: s + opts.batch]
            xb = x[b] if isinstance(x, Tensor) else x.rows(b)
            loss = loss_fn(net(xb), y[b], w[b])
            opt.zero_grad()
            (loss / w[b].sum()).backward()
            opt.step()
            if sched is not None:
                sched.step()
        if checkpoint is not None:
            checkpoint.save({"net": net.state_dict(), "opt": opt.state_dict(),
                             "sched": sched.state_dict() if sched is not None else None,
                             "gen": gen.get_state(), "epoch": epoch + 1})
    net.eval()


def standardised(model: BoxRanker, x: Tensor, dropped: Sequence[int] = ()) -> Tensor:
    """``x`` (``float [n, F]``, the model's columns) as the model's MLPs read it
    (:meth:`~reeb_torch.ranker.BoxRanker.standardise`), the columns ``dropped`` at their mean (0)."""
    xs = model.standardise(x)
    xs[:, list(dropped)] = 0.0
    return xs


def quality_rows(iou: Tensor, object_weight: Tensor, x: Tensor | RowView, label: Tensor, grade: tuple[float, float],
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
