"""The learned ranking's cross-validation (``reeb fit``'s estimate, the paired benchmarks):
fit on all blocks of frames but one, score the held-out block with that model.

* :func:`cross_validate` splits the frames into blocks
  (:func:`~reeb_torch.tuning.fold_blocks`), fits on all blocks but one
  (:func:`~reeb_torch.ranker.fit.fit_ranker`), keeping the held-out block's drive neighbours out
  (:func:`~reeb_torch.ranker.frames.training_frames`), scores the generator with that model on the
  held-out block, and collects the held-out hits (:func:`~reeb_torch.tuning.held_out`).
* :func:`held_out_outputs` gives each frame's proposals from the model that never saw it.
* :func:`kept_rows`: the rows of the candidates a fitted prefilter keeps
  (:attr:`~reeb_torch.ranker.fit.FitOptions.hard_negatives`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor
from torchvision.ops import box_iou

from ..config import ReebConfig
from ..metrics.recall import best_iou, object_hits
from ..ranker import BoxRanker, fit as RF, keep_candidates, save_ranker
from ..ranker.store import Checkpoints, StoredFrames
from ..tuning import FrameCache, fold_blocks, held_out
from . import frames as F

__all__ = ["FitCrossValidation", "cross_validate", "held_out_outputs", "best_ious", "hinted_classes", "kept_rows"]


def kept_rows(cache: FrameCache, cfg: ReebConfig, opts: RF.FitOptions,
              indices: Sequence[int]) -> Callable[[BoxRanker], list[RF.Sample]]:
    """For :attr:`~reeb_torch.ranker.fit.FitOptions.hard_negatives`: a function of a model
    with a fitted prefilter that gives, per frame of ``indices`` of ``cache``,
    :func:`~reeb_torch.ranker.frames.frame_sample`'s rows of the candidates the prefilter keeps
    under ``cfg`` (:func:`~reeb_torch.ranker.keep_candidates`, as
    :meth:`~reeb_torch.ranker.LearnedRanking.rank` keeps them), the negatives drawn at
    ``opts.hard_negatives`` by a generator seeded with ``(opts.seed, i, 4)``."""
    unranked = cfg.unranked()
    hard = dataclasses.replace(opts, negatives=opts.hard_negatives, quality_hidden=None, refine_hidden=None)
    frames = cache.frames

    def rows(model: BoxRanker) -> list[RF.Sample]:
        def frame(i: int) -> RF.Sample:
            c = cache.candidates(unranked, i)
            names = list(c.feature_names)
            cheap = c.features[:, [names.index(n) for n in model.feature_names[: model.cheap]]]
            sel = keep_candidates(lambda: c.scores, lambda: model.prefilter_scores(cheap), torch.tensor([len(cheap)]),
                                  cfg.ranker_keep, cfg.ranker_v_share)
            ignore = frames.ignore[i] if isinstance(frames, F.FitFrames) else torch.zeros(0, 4)
            return F.frame_sample(c.features[sel], c.boxes[sel], frames.gts[i], frames.labels[i], ignore, hard,
                                  np.random.default_rng([opts.seed, i, 4]))

        return [frame(i) for i in indices]

    return rows


@dataclass
class FitCrossValidation:
    """Held-out recall of fitted rankings against a base config on the same frames.

    Attributes:
        folds: the frame indices of each held-out block.
        ranked_hits, base_hits: per frame (in frame order), ``bool [N_i]``: the objects the
            generator with the model fitted without that frame's block finds, and ``base``'s.
        per_fold: per block, ``(ranked recall, base recall)``.
        trained: per block, how many frames its model was fitted on.
        hinted: per frame, ``int64 [N_i]``: the class (index into the frames' classes) the
            held-out model hints for each object it finds (:func:`hinted_classes`), -1 for
            one it misses or where the model has no class head.
        also_hits: per config of :func:`cross_validate`'s ``also``, per frame, its hits with
            the same held-out models (settings that act after the model, paired exactly).
        ranked_best, also_best: with :func:`cross_validate`'s ``best_ks``, per frame
            ``float32 [N_i, len(best_ks)]``: each object's best IoU with the top ``k`` proposals
            of the ranked config (and of each ``also`` config) for each ``k`` (recall at any
            IoU, AR); empty otherwise.
    """

    folds: list[list[int]]
    ranked_hits: list[Tensor] = field(repr=False)
    base_hits: list[Tensor] = field(repr=False)
    per_fold: list[tuple[float, float]] = field(default_factory=list)
    hinted: list[Tensor] = field(default_factory=list, repr=False)
    trained: list[int] = field(default_factory=list)
    also_hits: list[list[Tensor]] = field(default_factory=list, repr=False)
    ranked_best: list[Tensor] = field(default_factory=list, repr=False)
    also_best: list[list[Tensor]] = field(default_factory=list, repr=False)


def best_ious(outputs: Sequence[dict[str, Tensor]], gts: Sequence[Tensor], ks: Sequence[int]) -> list[Tensor]:
    """Per frame, ``float32 [N_i, len(ks)]``: each object's (``gts[i]``) best IoU with the top
    ``k`` boxes of ``outputs[i]``, for each ``k`` of ``ks``."""

    return [torch.stack([best_iou(o["boxes"], g, k).float() for k in ks], 1) if len(g)
            else torch.zeros(0, len(ks)) for o, g in zip(outputs, gts)]


def hinted_classes(outputs: Sequence[dict[str, Tensor]], gts: Sequence[Tensor], k: int = 2000,
                   iou: float = 0.7) -> list[Tensor]:
    """Per frame, ``int64 [N_i]``: for each object (``gts[i]``, ``[N_i, 4]``) that the top
    ``k`` proposals find at ``iou``, the class hinted (``labels``) by the proposal that
    overlaps it most; -1 where none finds it, or the outputs hold no ``labels``."""
    out = []
    for o, g in zip(outputs, gts):
        hint = torch.full((len(g),), -1, dtype=torch.long)
        boxes = o["boxes"][:k]
        if len(g) and len(boxes) and "labels" in o:
            best, which = box_iou(g.float(), boxes.float()).max(1)
            found = best >= iou
            hint[found] = o["labels"][:k][which[found]]
        out.append(hint)
    return out


class _HeldOutModels:
    """The models fitted without each block of frames (``folds`` blocks of
    :func:`~reeb_torch.tuning.fold_blocks`, or the blocks ``folds``), in a temporary folder
    removed on leaving the ``with`` block: :meth:`fit` fits block ``f``'s, keeping every
    drive neighbour and near-copy of the block out of its training frames
    (:func:`~reeb_torch.ranker.frames.training_frames`), and records how many frames it was fitted on. ``scratch``: the
    folder the temporary one is made in (default: the system's)."""

    def __init__(self, cache: FrameCache, names: Sequence[str], samples: Sequence[RF.Sample] | StoredFrames,
                 opts: RF.FitOptions, folds: int | Sequence[Sequence[int]], gap: int,
                 scratch: str | os.PathLike | None = None, cfg: ReebConfig | None = None,
                 keep: str | os.PathLike | None = None) -> None:
        frames = cache.frames
        self.frames, self.names, self.samples, self.opts, self.gap = frames, names, samples, opts, gap
        self.cache, self.cfg = cache, cfg if cfg is not None else ReebConfig()
        self.blocks = fold_blocks(len(frames), folds) if isinstance(folds, int) else [list(b) for b in folds]
        self.similar = F.similar_frames(frames.images)
        self.trained: list[int] = []
        self._tmp = None if keep is not None else tempfile.TemporaryDirectory(prefix="reeb-fit-", dir=scratch)
        self.keep: Path | None = None
        if keep is not None:  # each block's model and training state, found again after a kill
            digest = hashlib.sha256(json.dumps([dataclasses.asdict(opts), self.blocks, gap, list(names)],
                                               sort_keys=True, default=str).encode()).hexdigest()[:16]
            self.keep = Path(keep) / f"held-out-{digest}"

    def __enter__(self) -> _HeldOutModels:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()

    def fit(self, f: int) -> Path:
        """Fit the model without block ``f`` (or find the one fitted before a kill); its weights file."""
        frames = self.frames
        train = F.training_frames(self.blocks, f, frames.ids, frames.folders, self.similar, self.gap)
        folder = self.keep if self.keep is not None else Path(self._tmp.name)  # type: ignore[union-attr]
        path = folder / f"fold{f}.safetensors"
        self.trained.append(len(train))
        if self.keep is not None and path.exists():
            return path
        slots = None
        if self.keep is not None:
            states = Checkpoints(self.keep / f"fold{f}", [len(train)])
            slots = states.slot
        picked = self.samples.subset(train) if isinstance(self.samples, StoredFrames) else [self.samples[i]
                                                                                            for i in train]
        model = RF.fit_ranker(picked, self.names, self.opts, frames.classes,
                             kept_rows(self.cache, self.cfg, self.opts, train), checkpoints=slots)
        return save_ranker(model, path)


def held_out_outputs(cache: FrameCache, cfg: ReebConfig, samples: Sequence[RF.Sample] | StoredFrames, opts: RF.FitOptions,
                     folds: int | Sequence[Sequence[int]], gap: int = 2,
                     progress: Callable | None = None,
                     scratch: str | os.PathLike | None = None,
                     keep: str | os.PathLike | None = None,
                     reduce: Callable[[int, dict[str, Tensor]], Any] | None = None) -> list:
    """Per frame (in frame order), ``ProposalGenerator(cfg)``'s output dict with the ranking
    fitted without the frame's block (``folds`` blocks: the folds and models of
    :func:`cross_validate`; or the blocks given, the frame indices of each, covering every
    frame once; from ``samples`` = :func:`~reeb_torch.ranker.frames.frame_samples` under ``cfg``): proposals from a model
    that never saw the frame, for any recall table. ``reduce(i, output)``: what is kept of
    frame ``i``'s output in its place (its hits, say), so that the outputs are not all held.

    Raises:
        ValueError: fewer than 2 folds, or fewer frames than folds.
    """
    names = cache.candidates(cfg.unranked(), 0).feature_names
    out: list = [None] * len(cache.frames)
    with _HeldOutModels(cache, names, samples, opts, folds, gap, scratch, cfg, keep) as models:
        for f in progress(range(len(models.blocks))) if progress else range(len(models.blocks)):
            block = models.blocks[f]
            ranked = cfg.replace(ranker=str(models.fit(f)))
            for i in block:  # one frame's output at a time
                o = cache.outputs(ranked, [i])[0]
                out[i] = reduce(i, o) if reduce is not None else o
    return out


def cross_validate(cache: FrameCache, cfg: ReebConfig, base: ReebConfig, samples: Sequence[RF.Sample] | StoredFrames,
                   opts: RF.FitOptions, folds: int, k: int = 2000, iou: float = 0.7, gap: int = 2,
                   progress: Callable | None = None, also: Sequence[ReebConfig] = (),
                   scratch: str | os.PathLike | None = None, best_ks: Sequence[int] = (),
                   keep: str | os.PathLike | None = None) -> FitCrossValidation:
    """For each of ``folds`` blocks of frames: fit on the others (:func:`~reeb_torch.ranker.frames.training_frames`),
    run the generator of ``cfg`` with that model on the block, and pair its hits with
    ``base``'s on the same objects; each config of ``also`` (settings that act after the
    model: ``class_quota``, ``top_k``, ``refine_top``, ...) runs with the same model too
    (``also_hits``); with ``best_ks``, each object's best IoU at those proposal counts is kept
    too (``ranked_best``, ``also_best``: :func:`best_ious`); the loop over the blocks is
    :func:`~reeb_torch.tuning.held_out`'s. ``keep``: a folder where each block's model
    and its training states stay (:class:`~reeb_torch.ranker.store.Checkpoints`), so a killed
    run started again goes on from them (default: a temporary folder in ``scratch``)."""

    frames = cache.frames
    names = cache.candidates(cfg.unranked(), 0).feature_names
    hinted: list[Tensor] = []
    also_hits: list[list[Tensor]] = [[] for _ in also]
    ranked_best: list[Tensor] = []
    also_best: list[list[Tensor]] = [[] for _ in also] if best_ks else []
    path: list[Path] = []  # the current block's model

    def fitted(f: int) -> ReebConfig:
        path[:] = [models.fit(f)]
        return cfg.replace(ranker=str(path[0]))

    def each(block: list[int], outputs: list[dict[str, Tensor]]) -> None:
        gts = [frames.gts[i] for i in block]
        hinted.extend(hinted_classes(outputs, gts, k, iou))
        if best_ks:
            ranked_best.extend(best_ious(outputs, gts, best_ks))
        for j, (other, hits) in enumerate(zip(also, also_hits)):
            outs = cache.outputs(other.replace(ranker=str(path[0])), block)
            hits += object_hits([o["boxes"] for o in outs], gts, k, iou)
            if best_ks:
                also_best[j].extend(best_ious(outs, gts, best_ks))

    with _HeldOutModels(cache, names, samples, opts, folds, gap, scratch, cfg, keep) as models:
        scored = held_out(cache, models.blocks, fitted, base, k, iou, each=each, progress=progress)
    return FitCrossValidation(models.blocks, scored.hits, scored.base_hits, per_fold=scored.per_fold,
                              trained=models.trained, hinted=hinted, also_hits=also_hits, ranked_best=ranked_best,
                              also_best=also_best)
