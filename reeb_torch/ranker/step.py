"""The learned ranking's step in the generator (``ReebConfig.ranker``; not in the paper).

:class:`LearnedRanking` takes REEB's candidates (eq. 9's cut), keeps each image's best by the
prefilter (and by V), computes their features (:mod:`reeb_torch.ranker.features`) and ranks
them by the model's logit (:class:`~reeb_torch.ranker.BoxRanker`); with a class head it also
hints each candidate's class (:meth:`LearnedRanking.class_map`, for ``class_quota``) and each
output box's (:meth:`LearnedRanking.class_hints`); where its weights hold a box refiner, it
refines the best output boxes (:meth:`LearnedRanking.refine`, ``ReebConfig.refine_top``).
"""

from __future__ import annotations

import copy
import json
import math
import warnings
from contextlib import nullcontext
from typing import Callable, ContextManager

import numpy as np
import torch
from torch import Tensor, nn

from ..config import CameraSettings, RankingSettings, ReebConfig, ScoreSettings, WindowSettings
from ..selection.grid_cache import GridCache
from ..selection.maps import ScoreMaps
from ..stages import windows as _windows
from ..stages._radix import kth_largest
from . import features as _features
from .model import BoxRanker, softmax_rows
from .orientation import ORIENTATION_NAMES, orientation_features, orientation_integrals
from .prefilter import prefilter_cpu
from .refine import merge_refined
from .weights import load_ranker

__all__ = ["CandidateFeatures", "LearnedRanking", "NOT_SEEN_BY_RANKER", "keep_candidates", "warn_if_fitted_elsewhere"]

NOT_SEEN_BY_RANKER: tuple[str, ...] = ("top_k", "ranker", "ranker_keep", "ranker_v_share", "nms_iou", "nms_iou_thin",
                                        "nms_thin_aspect", "rank_quality", "class_quota", "refine_top", "refine_class",
                                        "refine_order", "refine_steps", "refine_nms")
"""Fields a ranking model does not depend on (they act after it)."""


SAME_SETTING_REL_TOL = 1e-3
"""Two numbers of a setting are the same when they differ by less than this share (a value
written to 3 or 4 significant digits, as ``camera_height_m=1.676`` for a fitted 1.67575)."""


def _same(a: object, b: object) -> bool:
    """Whether two settings (JSON values) are the same: numbers within
    :data:`SAME_SETTING_REL_TOL` of each other, lists item by item, anything else equal."""
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=SAME_SETTING_REL_TOL, abs_tol=1e-12)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def warn_if_fitted_elsewhere(config: ReebConfig, fitted: dict | None) -> None:
    """Warn (once per setting) when ``config`` differs from the one the ranking model was fitted
    with in a field its features or candidates depend on (numbers beyond a rounding:
    :func:`_same`): it still runs, likely worse."""
    if not fitted:
        return

    now = json.loads(json.dumps(config.to_dict(), default=list))
    differ = [k for k, v in now.items() if k in fitted and k not in NOT_SEEN_BY_RANKER and not _same(fitted[k], v)]
    if differ:
        shown = ", ".join(f"{k}={now[k]!r} (fitted with {fitted[k]!r})" for k in differ[:3])
        more = f" and {len(differ) - 3} more" if len(differ) > 3 else ""
        warnings.warn(f"reeb: the ranker {config.ranker!r} was fitted with other settings: {shown}{more}; it "
                      "ranks these candidates, likely worse than on its own (reeb fit fits one for them)",
                      UserWarning, stacklevel=4)


def _chosen(chosen: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.nonzero(chosen, as_tuple=True)`` of a ``bool [B, N]`` mask: ``(bi, ni)``
    ``int64``, image-major, windows ascending. On the CPU numpy's ``flatnonzero``, an image
    at a time, several times faster than torch's 2-D nonzero on a batch's windows
    (docs/results.md, "What makes the CPU path fast")."""
    if chosen.device.type != "cpu":
        images, windows = torch.nonzero(chosen, as_tuple=True)
        return images, windows
    mask = chosen.numpy()
    parts = [np.flatnonzero(row) for row in mask]
    ni = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    bi = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    return torch.from_numpy(bi.astype(np.int64, copy=False)), torch.from_numpy(ni.astype(np.int64, copy=False))


def _gather(values: Tensor, bi: Tensor, ni: Tensor, counts: Tensor) -> Tensor:
    """``values[bi, ni]`` for :func:`_chosen`'s ``(bi, ni)`` (image-major, ``counts`` an
    image): on the CPU numpy's take, an image row at a time (faster than torch's 2-D gather
    on a frame's candidates)."""
    if values.device.type != "cpu":
        return values[bi, ni]
    rows, idx = values.numpy(), ni.numpy()
    parts, start = [], 0
    for b, n in enumerate(counts.tolist()):
        parts.append(np.take(rows[b], idx[start: start + n]))
        start += n
    return torch.from_numpy(np.concatenate(parts) if parts else rows.reshape(-1)[:0].copy())


def _best_per_image(values: Tensor, counts: Tensor, keep: int) -> Tensor:
    """Indices of the best ``keep`` of each image's ``values`` (the images' values lie in
    consecutive runs of ``counts``), ties to the earlier; ascending. On the CPU a compiled
    radix selection (:func:`~reeb_torch.stages._radix.kth_largest`), elsewhere a stable sort."""
    out, start = [], 0
    for n in counts.tolist():
        part = values[start: start + n]
        if n <= keep:
            sel = torch.arange(n, device=values.device)
        elif values.device.type == "cpu":
            v = part.detach().float().contiguous().numpy()
            thr = kth_largest(v, keep)
            mask = v > thr
            mask[np.flatnonzero(v == thr)[: keep - int(mask.sum())]] = True  # ascending, without a sort
            sel = torch.from_numpy(np.flatnonzero(mask))
        else:
            sel = torch.sort(part, descending=True, stable=True).indices[:keep].sort().values
        out.append(sel + start)
        start += n
    return torch.cat(out) if out else values.new_zeros(0, dtype=torch.long)


def keep_candidates(v: Callable[[], Tensor], prefilter: Callable[[], Tensor], counts: Tensor, keep: int,
                    v_share: float) -> Tensor:
    """Indices (ascending) of the candidates the learned ranking ranks: each image's best
    ``keep`` (the images' candidates lie in consecutive runs of ``counts``),
    ``round(v_share · keep)`` of them its best by V (``v()``, ``float [K]``) whatever the
    prefilter says, the rest its best by the prefilter's logit (``prefilter()``, ``float32
    [K]``); each is computed only where it is needed."""
    by_v = round(v_share * keep)
    if by_v >= keep:  # V alone
        return _best_per_image(v(), counts, keep)
    pre = prefilter()
    if by_v:  # each image's best by V first, whatever the prefilter says
        pre[_best_per_image(v(), counts, by_v)] = math.inf
    return _best_per_image(pre, counts, keep)


class CandidateFeatures:
    """The per-box features of one config's candidates (:mod:`reeb_torch.ranker.features`),
    what the learned ranking reads and ``reeb fit`` fits on; no model needed.

    Args:
        scores: V's settings (the location fit's classes, eq. 1's normaliser).
        camera: the camera's height and horizon row.
        windows: the windows' settings (each class's width range, ``object_templates``).
        orientation: also the edge-orientation columns
            (:data:`~reeb_torch.ranker.orientation.ORIENTATION_NAMES`, after the others).
    """

    def __init__(self, scores: ScoreSettings, camera: CameraSettings, windows: WindowSettings,
                 orientation: bool = True) -> None:
        self.scores, self.camera, self.windows = scores, camera, windows
        self.orientation = orientation
        self.cache = GridCache()
        """The window columns and the prefilter's table per window grid; per-device copies."""

    @classmethod
    def from_config(cls, config: ReebConfig, orientation: bool = True) -> "CandidateFeatures":
        """The features of ``config``'s candidates, given the parts' settings they read."""
        return cls(config.scores, config.camera, config.windows, orientation)

    def feature_names(self) -> tuple[str, ...]:
        """The columns of :meth:`features` for this config (one location fit per class)."""
        names = _features.feature_names(len(self.scores.class_heights_m))
        return names + ORIENTATION_NAMES if self.orientation else names

    def box_maps(self, maps: ScoreMaps, geometry_only: bool = False) -> _features.BoxMaps:
        """The tables the per-box features read (:class:`~reeb_torch.ranker.features.BoxMaps`);
        with ``geometry_only``, only their sizes (for the window columns: no table is built)."""
        grey = maps.grey
        widths = tuple((t[2], t[3]) for t in self.windows.object_templates)
        ii_edges = ii_grey = ii_grey2 = green = None
        tables = None
        if not geometry_only:
            assert grey is not None, "the per-box features read the grey image (ScoreMaps.grey)"
            ii_edges, ii_grey = maps.integral("edges"), maps.integral("grey")
            ii_grey2 = maps.integral_grey_squared()
            green, tables = maps.green, maps.tables()
        sc, cam = self.scores, self.camera
        return _features.BoxMaps(
            (maps.edges.shape[-2], maps.edges.shape[-1]), ii_edges, ii_grey, ii_grey2, green, tables, cam.horizon,
            cam.camera_height_m, tuple(h / cam.camera_height_m for h in sc.class_heights_m), tuple(sc.class_weights),
            widths, sc.ground_log_sigma, maps.fx, maps.fy, sc.center_fraction, sc.score_norm, sc.kappa, sc.gamma)

    def features(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, chosen: Tensor,
                 share: Tensor, entropy: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The features of every candidate: ``(bi int64 [K], ni int64 [K], float32 [K, F])``,
        the image and window index of each candidate (``nonzero(chosen)`` order) and its
        features (:func:`~reeb_torch.ranker.features.box_features`; compiled on the CPU)."""
        bi, ni = _chosen(chosen)
        return bi, ni, self.features_of(maps, grid, scores, share, entropy, bi, ni)

    def window_table(self, maps: ScoreMaps, grid: _windows.WindowGrid) -> Tensor:
        """The window columns of every window of ``grid`` (:func:`~reeb_torch.ranker.features.window_features`),
        ``float32 [N, 11 + C]`` (as the features hold them), computed once per grid."""
        dev = maps.edges.device

        def build() -> Tensor:
            boxes = self.cache.device_tensor(grid.boxes, dev).round().long()
            return _features.window_features(self.box_maps(maps, geometry_only=True), boxes).float()

        return self.cache.grid_cached(("window_features", maps.fx, maps.fy, str(dev)), grid, build)

    def features_of(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, share: Tensor,
                    entropy: Tensor, bi: Tensor, ni: Tensor, cheap: bool = False) -> Tensor:
        """The features of the candidates ``(bi, ni)`` (image, window: ``int64 [K]`` each),
        ``float32 [K, F]``; with ``cheap``, only the first :func:`~reeb_torch.ranker.features.cheap_count`
        columns. On the CPU one compiled pass (:func:`~reeb_torch.ranker.features.box_features_cpu`),
        elsewhere tensor ops (:func:`~reeb_torch.ranker.features.box_features`): the same numbers."""
        dev = scores.device
        region_of = self.cache.device_tensor(grid.region_of, dev)
        orient = self.orientation and not cheap
        if dev.type == "cpu":  # the orientation columns written into the last columns: no copy
            out = _features.box_features_cpu(self.box_maps(maps, geometry_only=cheap), grid.boxes,
                                             self.window_table(maps, grid), scores, share, entropy, region_of,
                                             bi, ni, cheap, extra=len(ORIENTATION_NAMES) if orient else 0)
            if orient:
                orientation_features(self._orientation_tables(maps), grid.boxes[ni].round().long(), bi,
                                     out[:, -len(ORIENTATION_NAMES):])
            return out
        boxes = self.cache.device_tensor(grid.boxes, dev)[ni].round().long()
        region = region_of[ni]
        out = _features.box_features(self.box_maps(maps, geometry_only=cheap), boxes, bi, scores[bi, ni],
                                     share[bi, region], entropy[bi, region], self.window_table(maps, grid)[ni],
                                     cheap)
        if not orient:
            return out
        return torch.cat([out, orientation_features(self._orientation_tables(maps), boxes, bi)], 1)

    @staticmethod
    def _orientation_tables(maps: ScoreMaps) -> Tensor:
        """The batch's orientation tables (:func:`~reeb_torch.ranker.orientation.orientation_integrals`
        of its grey images), built once per batch."""
        grey = maps.grey
        assert grey is not None, "the orientation columns read the grey image (ScoreMaps.grey)"
        return maps.kept("orientation", lambda: orientation_integrals(grey))

    def prefilter(self, model: BoxRanker, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor,
                  share: Tensor, entropy: Tensor, bi: Tensor, ni: Tensor) -> Tensor:
        """The prefilter's logit of each candidate ``(bi, ni)``, ``float32 [K]``: on the CPU,
        for a one-hidden-layer prefilter, the hidden layer's share of the window columns is
        tabulated once per grid and the rest compiled (:func:`~reeb_torch.ranker.prefilter.prefilter_cpu`);
        elsewhere the model on the cheap columns (the same to float32 rounding)."""
        pre = model.prefilter
        assert pre is not None, "this model has no prefilter"
        if scores.device.type != "cpu" or len(pre) != 3:
            return model.prefilter_scores(self.features_of(maps, grid, scores, share, entropy, bi, ni, cheap=True))
        first, last = pre[0], pre[2]
        assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)
        nw = self.window_table(maps, grid).shape[1]

        def build() -> Tensor:
            win = (self.window_table(maps, grid).float() - model.mean[:nw]) / model.scale[:nw]
            return torch.addmm(first.bias, win, first.weight[:, :nw].T).contiguous()

        table = self.cache.grid_cached(("prefilter", id(model)), grid, build)
        return prefilter_cpu(table, scores, share, entropy, grid.region_of, bi, ni, model.mean[nw: nw + 3],
                             model.scale[nw: nw + 3], first.weight[:, nw:], last.weight[0], float(last.bias[0]))


class LearnedRanking(CandidateFeatures):
    """The learned ranking: its model (``ranking.ranker``), the class quota's shares, and the
    candidates, ranked by their features.

    Args:
        ranking: the ranking's settings; ``ranking.ranker`` names the weights (not ``"none"``).
        scores, camera, windows: what the features read (:class:`CandidateFeatures`).
        top_k: the proposals of each image (where refined boxes go, :meth:`refine`).
    """

    def __init__(self, ranking: RankingSettings, scores: ScoreSettings, camera: CameraSettings,
                 windows: WindowSettings, top_k: int) -> None:
        # the columns the model reads: with or without the orientation columns
        orientation = set(ORIENTATION_NAMES) <= set(load_ranker(ranking.ranker).feature_names)
        super().__init__(scores, camera, windows, orientation=orientation)
        self.ranking, self.top_k = ranking, top_k
        self._models: dict[str, BoxRanker] = {}  # the model's copy per device other than the CPU
        self.model: BoxRanker = load_ranker(ranking.ranker, self.feature_names())
        """The :class:`~reeb_torch.ranker.BoxRanker` of ``ranking.ranker``."""
        self.class_share: tuple[float, ...] | None = ranking.class_shares(self.model.classes)
        """``ranking.class_quota`` as one share a class of the model's class head
        (:meth:`~reeb_torch.config.RankingSettings.class_shares`), or None: no class quota."""
        if ranking.class_quota and self.class_share is None:
            warnings.warn(f"ReebConfig.class_quota is ignored: the ranker {ranking.ranker!r} has no class head "
                          "(fit one with reeb fit, whose models have one by default)", UserWarning, stacklevel=4)
        if ranking.rank_quality and self.model.quality is None:
            warnings.warn(f"ReebConfig.rank_quality is ignored: the ranker {ranking.ranker!r} has no quality head "
                          "(FitOptions.quality_hidden fits one)", UserWarning, stacklevel=4)
        if ranking.refine_top and self.model.refiner is None:
            warnings.warn(f"ReebConfig.refine_top is ignored: the ranker {ranking.ranker!r} has no box refiner "
                          "(reeb fit --refiner fits one)", UserWarning, stacklevel=4)
        self.refine_class: int | None = None
        """The class head's index of ``ranking.refine_class``, or None: every box is refined."""
        if ranking.refine_class:
            classes = self.model.classes or ()
            if ranking.refine_class not in classes:
                raise ValueError(f"ReebConfig.refine_class {ranking.refine_class!r} is not a class of the ranker "
                                 f"{ranking.ranker!r}'s class head ({', '.join(classes) or 'it has none'})")
            self.refine_class = classes.index(ranking.refine_class)

    @classmethod
    def from_config(cls, config: ReebConfig, orientation: bool = True) -> "LearnedRanking":
        """The ranking of ``config`` (``config.ranker`` not ``"none"``), given the parts' settings
        it reads; warns where the model was fitted with other settings. (``orientation``: the
        model's columns decide it.)"""
        ranking = cls(config.ranking, config.scores, config.camera, config.windows, config.top_k)
        warn_if_fitted_elsewhere(config, ranking.model.meta.get("config"))
        return ranking

    def refines(self) -> bool:
        """Whether :meth:`refine` changes the output (``refine_top`` > 0 and a refiner)."""
        return self.ranking.refine_top > 0 and self.model.refiner is not None

    def refine(self, maps: ScoreMaps, results: list[dict[str, Tensor]]) -> list[dict[str, Tensor]]:
        """The output dicts of a batch (``boxes float32 [N_i, 4]`` in input pixels, ranked;
        ``scores``, and ``labels``, ``class_probs`` where hinted) with the best
        ``refine_top`` boxes of each (of those hinted ``refine_class``, where set) refined by the model's refiner
        (:meth:`~reeb_torch.ranker.refine.BoxRefiner.refine`, ``refine_steps`` times, on the
        batch's integral images) and put beside them (:func:`~reeb_torch.ranker.refine.merge_refined`:
        ``refine_order``, ``refine_nms``), at most ``top_k`` rows each; the dicts as they are
        without a refiner or with ``refine_top`` 0."""
        if not self.refines() or not results:
            return results
        dev = maps.edges.device
        refiner = self._model_on(dev).refiner
        assert refiner is not None  # refines() checked it
        which = []
        for r in results:
            if self.refine_class is not None and "labels" in r:
                which.append(torch.nonzero(r["labels"] == self.refine_class).squeeze(1)[: self.ranking.refine_top])
            else:
                which.append(torch.arange(min(self.ranking.refine_top, len(r["boxes"]))))
        tops = [r["boxes"][w].to(dev) for r, w in zip(results, which)]
        counts = [len(t) for t in tops]
        if not sum(counts):
            return results
        to_work = torch.tensor([maps.fx, maps.fy, maps.fx, maps.fy], device=dev)
        bi = torch.repeat_interleave(torch.arange(len(tops), device=dev), torch.tensor(counts, device=dev))
        size = (int(maps.edges.shape[-2]), int(maps.edges.shape[-1]))
        refined = refiner.refine(maps.integral("edges"), maps.integral("grey"), torch.cat(tops).float() * to_work, bi,
                                 self.camera.horizon, size, self.ranking.refine_steps) / to_work
        h_in, w_in = maps.input_size
        refined[:, 0::2] = refined[:, 0::2].clamp(0.0, float(w_in))
        refined[:, 1::2] = refined[:, 1::2].clamp(0.0, float(h_in))
        rk = self.ranking
        return [merge_refined(r, part.to(r["boxes"].device), rk.refine_order, self.top_k, rk.refine_nms, w)
                for r, part, w in zip(results, refined.split(counts), which)]

    def rank(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, chosen: Tensor, share: Tensor,
             entropy: Tensor, features_out: list[tuple[Tensor, Tensor, Tensor]] | None = None,
             timer: Callable[[str, torch.device], ContextManager] | None = None) -> tuple[Tensor, Tensor]:
        """The candidates ``chosen`` (``bool [B, N]``, eq. 9's cut of the windows scored
        ``scores``, ``float32 [B, N]``; ``share``, ``entropy``: ``[B, R]``) ranked by the model,
        for :meth:`~reeb_torch.selection.suppress.Suppression.suppress`: ``(scores float32 [B, N],
        chosen bool [B, N])``, the model's logit of each candidate it ranks
        (``-inf`` elsewhere) and which those are: where the model has a prefilter, each
        image's best ``ranker_keep`` candidates: ``ranker_v_share`` of them its best by V, the
        rest its best by the prefilter; all of them otherwise.
        ``features_out``, if given, gets ``(bi, ni, features)`` of the candidates it ranked
        (in ``nonzero(chosen)`` order), so that :meth:`class_hints` need not compute them again.
        ``timer(name, device)``, if given, times its parts (``ranker.prefilter``: the pairs, the
        prefilter and its cut; ``ranker.features``; ``ranker.model``: the MLP and the scatter)."""
        model = self._model_on(scores.device)
        dev = scores.device
        timed = timer if timer is not None else (lambda name, device: nullcontext())
        with timed("ranker.prefilter", dev):
            bi, ni = _chosen(chosen)
            keep = self.ranking.ranker_keep
            counts = torch.bincount(bi, minlength=scores.shape[0])
            if model.prefilter is not None and len(bi) and int(counts.max()) > keep:
                sel = keep_candidates(lambda: _gather(scores, bi, ni, counts),
                                      lambda: self.prefilter(model, maps, grid, scores, share, entropy, bi, ni),
                                      counts, keep, self.ranking.ranker_v_share)
                bi, ni = bi[sel], ni[sel]
        out = torch.full_like(scores, -math.inf)
        kept = torch.zeros_like(chosen)
        if len(bi):
            with timed("ranker.features", dev):
                feats = self.features_of(maps, grid, scores, share, entropy, bi, ni)
            with timed("ranker.model", dev):
                logit = model.rank(feats)
                if self.ranking.rank_quality and model.quality is not None:
                    logit += self.ranking.rank_quality * torch.sigmoid(model.quality_logits(feats))
                out[bi, ni] = logit
                kept[bi, ni] = True
            if features_out is not None:
                features_out.append((bi, ni, feats))
        return out, kept

    def class_map(self, ranked: tuple[Tensor, Tensor, Tensor], shape: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """``int8 [B, N]``: the class the model's head hints for each candidate :meth:`rank`
        ranked (``ranked``: its ``(bi, ni, features)``; the index into the model's classes),
        ``-1`` elsewhere: what ``class_quota`` shares the output by
        (:meth:`~reeb_torch.selection.suppress.Suppression.suppress`); and the head's logits of
        those candidates, ``float32 [K, C]`` in their order (so that :meth:`class_hints` need
        not run the head again over the output)."""
        bi, ni, feats = ranked
        out = torch.full(shape, -1, dtype=torch.int8, device=feats.device)
        model = self._model_on(feats.device)
        logits = feats.new_zeros(0, len(model.classes or ()))
        if len(bi):
            logits = model.class_logits(feats)
            out[bi, ni] = logits.argmax(1).to(torch.int8)
        return out, logits

    def class_hints(self, maps: ScoreMaps, grid: _windows.WindowGrid, scores: Tensor, share: Tensor,
                    entropy: Tensor, windows: list[Tensor],
                    ranked: tuple[Tensor, Tensor, Tensor] | None = None,
                    ranked_logits: Tensor | None = None) -> list[Tensor]:
        """The class head's probabilities (:meth:`~reeb_torch.ranker.BoxRanker.class_probs`) of
        the windows ``windows[i]`` (``int64 [N_i]``) of each image, ``float32 [N_i, C]``, from
        their features under REEB's scores V (``scores [B, N]``, before the learned ranking).
        ``ranked``: :meth:`rank`'s ``(bi, ni, features)`` under the same V; the rows of
        the windows among them are taken from there (the same numbers), the others computed.
        ``ranked_logits``: :meth:`class_map`'s logits of those rows, if it ran; the windows
        among them take their logits from there (the same numbers: the head runs row by row)."""
        model = self._model_on(scores.device)
        counts = [len(w) for w in windows]
        dev = scores.device
        bi = torch.repeat_interleave(torch.arange(len(windows), device=dev), torch.tensor(counts, device=dev))
        ni = torch.cat(windows).to(dev) if windows else bi
        if not len(ni):
            return [scores.new_zeros(0, len(model.classes or ())) for _ in windows]
        if ranked is not None and len(ranked[0]):
            rb, rn, rf = ranked
            n = scores.shape[1]
            known = rb * n + rn  # ascending: nonzero order
            key = bi * n + ni
            at = torch.searchsorted(known, key).clamp_(max=len(known) - 1)
            miss = known.index_select(0, at) != key
            if ranked_logits is not None:  # the head's logits of the ranked rows: only the misses run it
                logits = ranked_logits.index_select(0, at)
                if bool(miss.any()):
                    logits[miss] = model.class_logits(
                        self.features_of(maps, grid, scores, share, entropy, bi[miss], ni[miss]))
                return list(softmax_rows(logits).split(counts))
            feats = rf.index_select(0, at)
            if bool(miss.any()):
                feats[miss] = self.features_of(maps, grid, scores, share, entropy, bi[miss], ni[miss])
        else:
            feats = self.features_of(maps, grid, scores, share, entropy, bi, ni)
        probs = model.class_probs(feats)
        return list(probs.split(counts))

    def _model_on(self, device: torch.device) -> BoxRanker:
        """:attr:`model` on ``device`` (the shared CPU model, or a copy per device)."""
        if device.type == "cpu":
            return self.model
        key = str(device)
        if key not in self._models:
            self._models[key] = copy.deepcopy(self.model).to(device)
        return self._models[key]
