"""The learned ranking's model: small MLPs over per-box features, giving one logit per box.

:class:`BoxRanker` standardises the features (the mean and spread of the frames it was
fitted on, kept as buffers) and has two stages, a cascade as BING's and Viola-Jones':

* :meth:`BoxRanker.prefilter_scores`: a tiny MLP over the first, cheap columns
  (:func:`~reeb_torch.ranker.features.cheap_count`: the window's geometry and location fits,
  V, the region), which need no box sum, for every candidate; the generator keeps the best
  ``ReebConfig.ranker_keep``;
* :meth:`BoxRanker.forward`: one or more MLPs over all the columns of those, averaged.

It is a plain ``nn.Module`` whose weights come from :func:`reeb_torch.ranker.load_ranker`;
the features are :func:`reeb_torch.ranker.features.box_features`.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from .features import cheap_count
from .refine import BoxRefiner, refine_feature_names


__all__ = ["BoxRanker", "RANK_ROWS", "softmax_rows"]

RANK_ROWS = 4096
"""Rows :meth:`BoxRanker.rank` takes at a time (a block's ``[rows, 64]`` activations, 1 MiB,
stay in a core's L2 cache between the layers)."""


def softmax_rows(logits: Tensor) -> Tensor:
    """The softmax of each row of ``logits`` ``float [K, C]``, ``float32 [K, C]``: along the
    rows of the transposed logits (torch's softmax over a last dimension of 4 was 8x slower
    than over a contiguous first one)."""
    return torch.softmax(logits.T.contiguous(), 0).T.contiguous()


def _mlp(inputs: int, hidden: Sequence[int], outputs: int = 1) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), nn.ReLU()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    return nn.Sequential(*layers)


class BoxRanker(nn.Module):
    """``forward(features float [K, F]) -> float32 [K]`` logits: higher ranks first.

    Args:
        feature_names: the ``F`` feature columns it reads, in order
            (:func:`reeb_torch.ranker.features.feature_names`).
        hidden: the widths of the hidden layers of each MLP.
        members: how many MLPs (fitted from different seeds) are averaged.
        prefilter: the widths of the prefilter's hidden layers (``()``: a linear prefilter),
            or None for none (every candidate gets all the features).
        classes: the object classes a box may be hinted as (e.g. ``("Car", "Pedestrian",
            "Cyclist", "Truck")``), or None for no class head.
        class_hidden: the widths of the class head's hidden layers.
        refine_hidden: the widths of the box refiner's hidden layers
            (:class:`~reeb_torch.ranker.refine.BoxRefiner`), or None for no refiner.
        quality_hidden: the widths of the localisation-quality head's hidden layers
            (:meth:`quality_logits`), or None for none.

    Attributes:
        mean, scale: ``float32 [F]`` buffers; a feature enters the MLPs as ``(x − mean) / scale``.
        meta: what the weights file said about itself (provenance, the config it was fitted
            with); ``{}`` for a model made here.
    """

    mean: Tensor
    scale: Tensor
    members: nn.ModuleList
    prefilter: nn.Sequential | None
    classifier: nn.Sequential | None
    refiner: BoxRefiner | None
    quality: nn.Sequential | None

    def __init__(self, feature_names: Sequence[str], hidden: Sequence[int] = (64, 64), members: int = 1,
                 prefilter: Sequence[int] | None = (16,), classes: Sequence[str] | None = None,
                 class_hidden: Sequence[int] = (32,), refine_hidden: Sequence[int] | None = None,
                 quality_hidden: Sequence[int] | None = None) -> None:
        super().__init__()
        if members < 1 or not hidden or min(hidden) < 1 or (prefilter and min(prefilter) < 1) \
                or (classes is not None and (len(classes) < 2 or (class_hidden and min(class_hidden) < 1))):
            raise ValueError(f"BoxRanker needs members >= 1, hidden widths >= 1 and 2 classes or more, got {members}, "
                             f"{tuple(hidden)}, prefilter {prefilter}, classes {classes}, class_hidden {class_hidden}")
        self.feature_names = tuple(feature_names)
        self.hidden = tuple(int(h) for h in hidden)
        f = len(self.feature_names)
        self.register_buffer("mean", torch.zeros(f))
        self.register_buffer("scale", torch.ones(f))
        self.members = nn.ModuleList(_mlp(f, self.hidden) for _ in range(members))
        self.prefilter_hidden = None if prefilter is None else tuple(int(h) for h in prefilter)
        self.cheap = cheap_count(sum(1 for n in self.feature_names if n.startswith("class_fit_")))
        """How many first columns the prefilter reads (:func:`~reeb_torch.ranker.features.cheap_count`)."""
        self.prefilter = None if prefilter is None else _mlp(self.cheap, prefilter)
        self.classes = None if classes is None else tuple(str(c) for c in classes)
        """The classes of :meth:`class_probs`'s columns, or None without a class head."""
        self.class_hidden = tuple(int(h) for h in class_hidden)
        self.classifier = None if classes is None else _mlp(f, self.class_hidden, len(classes))
        """The class head: which class a box looks like, were it an object (softmax logits)."""
        self.refiner = None if refine_hidden is None else BoxRefiner(refine_feature_names(), refine_hidden)
        """The box refiner (side offsets of the output boxes, ``ReebConfig.refine_top``), or None."""
        self.quality = None
        self.quality_hidden: tuple[int, ...] | None = None
        if quality_hidden is not None:
            self.set_quality(quality_hidden)
        self.meta: dict = {}

    def set_quality(self, hidden: Sequence[int]) -> None:
        """Give the model a new localisation-quality head (:meth:`quality_logits`) with hidden
        layers ``hidden`` (``()``: linear), in place of any it had."""
        if hidden and min(hidden) < 1:
            raise ValueError(f"BoxRanker's quality head needs widths >= 1, got {tuple(hidden)}")
        self.quality_hidden = tuple(int(h) for h in hidden)
        self.quality = _mlp(len(self.feature_names), self.quality_hidden)
        """The localisation-quality head: how tight a box is on its object, were it on one."""

    def extra_repr(self) -> str:
        return (f"features={len(self.feature_names)}, hidden={self.hidden}, members={len(self.members)}, "
                f"prefilter={self.prefilter_hidden}, classes={self.classes}, "
                f"refiner={None if self.refiner is None else self.refiner.hidden}, quality={self.quality_hidden}")

    def prefilter_scores(self, cheap: Tensor) -> Tensor:
        """``float [K, cheap]`` (the first :attr:`cheap` columns of the features) -> ``float32 [K]``
        the prefilter's logits; higher is kept first. Raises ValueError without a prefilter."""
        if self.prefilter is None:
            raise ValueError("this BoxRanker has no prefilter")
        if cheap.ndim != 2 or cheap.shape[1] != self.cheap:
            raise ValueError(f"BoxRanker.prefilter_scores expects [K, {self.cheap}], got {tuple(cheap.shape)}")
        x = (cheap.float() - self.mean[: self.cheap]) / self.scale[: self.cheap]
        return self.prefilter(x).squeeze(1)

    @torch.no_grad()
    def class_logits(self, features: Tensor) -> Tensor:
        """``float [K, F] -> float32 [K, C]``: the class head's logits of each box over
        :attr:`classes` (their argmax is :meth:`class_probs`'s), computed as :meth:`rank`
        computes the ranking's: the standardisation folded into the first layer, the rows in
        blocks. Raises ValueError without a class head."""
        if self.classifier is None or self.classes is None:
            raise ValueError("this BoxRanker has no class head (fit one with reeb fit)")
        self._check(features)
        return self._run_folded([self._folded(self.classifier)], features.float(), len(self.classes))

    @torch.no_grad()
    def class_probs(self, features: Tensor) -> Tensor:
        """``float [K, F] -> float32 [K, C]``: for each box, the probability of each of
        :attr:`classes` were it an object (rows sum to 1; the class head was fitted on the
        boxes that overlap an object at IoU ≥ 0.7): the softmax of :meth:`class_logits`.
        Raises ValueError without a class head."""
        return softmax_rows(self.class_logits(features))

    @torch.no_grad()
    def quality_logits(self, features: Tensor) -> Tensor:
        """``float [K, F] -> float32 [K]``: the quality head's logit of each box, how tight it
        is on its object were it on one (fitted on the boxes at IoU ≥ 0.5 with an object, to
        their IoU graded to [0, 1]), computed as :meth:`rank` computes the ranking's. Raises
        ValueError without a quality head."""
        if self.quality is None:
            raise ValueError("this BoxRanker has no quality head (FitOptions.quality_hidden fits one)")
        self._check(features)
        return self._run_folded([self._folded(self.quality)], features.float(), 1).squeeze(1)

    def _check(self, features: Tensor) -> None:
        if features.ndim != 2 or features.shape[1] != len(self.feature_names):
            raise ValueError(f"BoxRanker expects features of shape [K, {len(self.feature_names)}], "
                             f"got {tuple(features.shape)}")

    @torch.no_grad()
    def ignore_columns(self, cols: Sequence[int]) -> None:
        """Set every MLP's first-layer weights from the feature columns ``cols`` to zero, so
        its output does not depend on them (the prefilter skips those past its cheap columns)."""
        for net in [*self.members, self.prefilter, self.classifier, self.quality]:
            if net is not None and len(cols):
                first = net[0]
                assert isinstance(first, nn.Linear)
                first.weight[:, [c for c in cols if c < first.in_features]] = 0.0

    def standardise(self, features: Tensor) -> Tensor:
        """``(features − mean) / scale``, float32."""
        return (features.float() - self.mean) / self.scale

    @torch.no_grad()
    def rank(self, features: Tensor) -> Tensor:
        """:meth:`forward` for inference (what the generator calls), ``float [K, F] -> float32
        [K]``: the standardisation folded into each MLP's first layer (weights ``W / scale``,
        bias ``b − (W / scale) · mean``), the rows taken :data:`RANK_ROWS` at a time (so each
        block's hidden activations stay in the core's cache between the layers: at batch 8,
        ~50000 rows a core, the whole ``[K, hidden]`` would not) and the activations computed
        in place. The same logits to float32 rounding (~1e-5)."""
        self._check(features)
        out = self._run_folded([self._folded(m) for m in self.members], features.float(), 1).squeeze(1)
        return out / len(self.members) if len(self.members) > 1 else out

    def _folded(self, mlp: nn.Module) -> list[tuple[Tensor, Tensor]]:
        """``mlp``'s layers as ``(bias, weight.T)`` with the standardisation folded into the
        first (weights ``W / scale``, bias ``b − (W / scale) · mean``)."""
        layers = [m for m in mlp.children() if isinstance(m, nn.Linear)]
        w = layers[0].weight / self.scale
        return [(layers[0].bias - w @ self.mean, w.T)] + [(layer.bias, layer.weight.T) for layer in layers[1:]]

    @staticmethod
    def _run_folded(mlps: list[list[tuple[Tensor, Tensor]]], x: Tensor, outputs: int) -> Tensor:
        """The sum of the folded ``mlps`` (ReLU between layers) over the rows of ``x``,
        ``float32 [K, outputs]``, :data:`RANK_ROWS` rows at a time, activations in place."""
        out = x.new_empty(len(x), outputs)
        for start in range(0, len(x), RANK_ROWS):
            rows = x[start: start + RANK_ROWS]
            acc: Tensor | None = None
            for layers in mlps:
                h = rows
                for i, (bias, weight_t) in enumerate(layers):
                    h = torch.addmm(bias, h, weight_t)
                    if i < len(layers) - 1:
                        h.relu_()
                acc = h if acc is None else acc.add_(h)
            assert acc is not None  # one MLP at least
            out[start: start + len(rows)] = acc
        return out

    def forward(self, features: Tensor) -> Tensor:
        self._check(features)
        x = self.standardise(features)
        out = self.members[0](x)
        for m in self.members[1:]:
            out = out + m(x)
        return (out / len(self.members)).squeeze(1)
