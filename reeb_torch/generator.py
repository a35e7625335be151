"""The REEB proposal generator: images in, ranked boxes out (the paper's Table 1).

``ProposalGenerator._propose_batch`` reads top to bottom as the paper's pseudo-code, one
call per stage: edge map, edge groups, road mask, regions with their entropy and budget,
dense windows, scores, the per-region cut, NMS. The
stages are functions in :mod:`reeb_torch.stages`; how windows are scored, cut and
suppressed (compiled or tensor paths, the batch's tables) is :mod:`reeb_torch.selection`;
the learned ranking of the candidates (not in the paper) is :mod:`reeb_torch.ranker`.
A batch of equal-sized images is computed as one batch; a list of images of different
sizes is split into equal-size batches.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import warnings
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import ImageBatch, check_images, check_range
from ._warm import Notice, gc_paused, start_helper, stop_helper, warm_picture
from .config import FRONT_END_FIELDS, ReebConfig
from .ranker import CandidateFeatures, LearnedRanking
from .selection import ScoreMaps, WindowSelection
from .stages import _scratch
from .stages._threads import on_two_cores, serially, torch_single_threaded
from .stages import edges as _edges
from .stages import groups as _groups
from .stages import road as _road
from .stages import scoring as _scoring
from .stages.windows import WindowGrid

__all__ = ["ProposalGenerator", "propose", "Inspection", "Candidates", "Working", "FrontEnd", "Trace", "warmup",
           "FRONT_END_FIELDS"]



_STAGE_LOCK = threading.Lock()  # stage_times is written by both halves of a CPU batch
_WARN_LOCK = threading.Lock()  # and both halves may find an empty image at once: one warns
_TIME_SHARE = threading.local()  # .share: the part of a stage's time this thread records
_WARM: set[tuple] = set()  # kernel keys (_kernel_key) of the configs this process has warmed up


@dataclass
class Inspection:
    """Everything :meth:`ProposalGenerator.inspect` computed for one image, at input
    resolution (``H × W``).

    Attributes:
        boxes: ``float32 [N, 4]`` proposals (x1, y1, x2, y2), ranked best first.
        scores: ``float32 [N]`` their combined scores V (eq. 12), descending.
        edges: ``float32 [H, W]`` edge magnitudes in [0, 1] after thresholding (Sec. 3.4).
        road_mask: ``bool [H, W]`` road pixels (eqs. 3–4).
        regions: ``float32 [R, 4]`` the region strips (x1, y1, x2, y2).
        entropy: ``float32 [R]`` Shannon entropy of each region in bits (eq. 2).
        share: ``float32 [R]`` fraction of the region's candidate budget it gets (eq. 9).
        num_groups: number of edge groups (Sec. 3.7).
        num_windows: number of sliding windows scored.
        labels: ``int64 [N]`` the class hint of each box (indices into
            :attr:`ProposalGenerator.classes`), or None where the settings give none.
    """

    boxes: Tensor
    scores: Tensor
    edges: Tensor
    road_mask: Tensor
    regions: Tensor
    entropy: Tensor
    share: Tensor
    num_groups: int
    num_windows: int
    labels: Tensor | None = None


@dataclass
class Candidates:
    """The candidates of one image that the learned ranking orders (the region cut, eq. 9),
    with their per-box features (:meth:`ProposalGenerator.candidates`).

    Attributes:
        boxes: ``float32 [K, 4]`` (x1, y1, x2, y2) in input pixels, in window order (not ranked).
        scores: ``float32 [K]`` their combined scores V (eq. 12).
        features: ``float32 [K, F]`` their features (:func:`reeb_torch.ranker.features.box_features`).
        feature_names: the ``F`` column names.
    """

    boxes: Tensor
    scores: Tensor
    features: Tensor
    feature_names: tuple[str, ...]


@dataclass
class Working:
    """The batch at the working resolution ``h × w``, as the edge stage (Sec. 3.4) leaves it.

    Attributes:
        gray: ``float32 (B, 1, h, w)`` grey images.
        edges: ``float32 (B, h, w)`` edge magnitudes.
        colour: ``float32 (B, 3, h, w)`` colour images, only where a stage reads them (the road
            mask), else None.
        green: ``int32 (B, h + 1, w + 1)`` green-pixel counts, for the vegetation term, or None.
    """

    gray: Tensor
    edges: Tensor
    colour: Tensor | None
    green: Tensor | None


class FrontEnd(NamedTuple):
    """:meth:`ProposalGenerator.front_end` of a batch of equal-sized images: what only
    :data:`FRONT_END_FIELDS` change, so that configs equal in those can share it
    (``working, maps = front`` unpacks it).

    Attributes:
        working: the batch at the working resolution (:class:`Working`).
        maps: the score maps (edges, groups, road mask), whose tables are built on first use
            (:class:`~reeb_torch.selection.ScoreMaps`).
    """

    working: Working
    maps: ScoreMaps


@dataclass
class Trace:
    """What the back end saw of one batch of ``B`` images of ``N`` windows and ``R`` regions
    (:meth:`ProposalGenerator.trace`); copies, not the memory the next call reuses.

    Attributes:
        scores: ``float32 [B, N]`` V (eq. 12) of every window (``-inf``: dropped by the score),
            as the region cut saw them.
        grid: the windows (:class:`~reeb_torch.stages.windows.WindowGrid`).
        chosen: ``bool [B, N]`` the region cut's candidates (eq. 9).
        share: ``float32 [B, R]`` each region's share of the budget (eq. 9).
        ranked: ``float32 [B, N]`` the learned ranking's logit of each candidate it ranked
            (``-inf`` elsewhere), or None without a ranker.
        kept: ``bool [B, N]`` the candidates it ranked, or None without a ranker.
    """

    scores: Tensor
    grid: WindowGrid
    chosen: Tensor
    share: Tensor
    ranked: Tensor | None = None
    kept: Tensor | None = None


class ProposalGenerator(nn.Module):
    """Region Enhanced Edge-Based (REEB) object proposals; no parameters, no training.

    Args:
        config: a :class:`ReebConfig` (default: ``ReebConfig()``, the best measured variant).
        **overrides: fields of the config to change, e.g. ``top_k=500``.

    ``forward(images)`` accepts a float ``(B, 3, H, W)`` tensor of RGB values in [0, 1], a
    ``uint8`` tensor of the same shape, or a list of ``(3, H, W)`` tensors of any sizes,
    on any device; it returns one dict per image with

    * ``boxes``: ``float32 [N, 4]`` (x1, y1, x2, y2) in that image's pixels, ranked;
    * ``scores``: ``float32 [N]``, descending; ``N <= config.top_k``;
    * with a ranking model that has a class head (the shipped ``kitti`` one: Car,
      Pedestrian, Cyclist, Truck; :attr:`classes`), also ``labels``: ``int64 [N]``, the
      index in :attr:`classes` of the class each box looks like, and ``class_probs``:
      ``float32 [N, C]``, the head's probability of each class were the box an object (a
      hint, not a detection: the boxes are class-agnostic proposals).

    On the CPU a call runs compiled kernels on two threads (the calling thread and one
    helper, each taking half the images through the whole algorithm; one image has each
    kernel's work split instead), with torch's intra-op threads set to 1 for its duration
    (restored after), and
    reuses the previous call's scratch memory for its large intermediate arrays (about
    8 MB per 1242×375 image, kept per thread; ``reeb_torch.stages._scratch.release()``
    frees it). The returned tensors never share that memory.
    """

    def __init__(self, config: ReebConfig | None = None, **overrides: object) -> None:
        super().__init__()
        cfg = config if config is not None else ReebConfig()
        if not isinstance(cfg, ReebConfig):
            raise TypeError(f"config must be a ReebConfig, got {type(cfg).__name__}")
        self.config = cfg.replace(**overrides) if overrides else cfg
        self.selection = WindowSelection.from_config(self.config)
        """The :class:`~reeb_torch.selection.WindowSelection` that scores, cuts and
        suppresses the windows, each of its parts given its own settings; another selection
        put here tries another cut (``benchmarks/selection_variants.py``)."""
        self.ranker = LearnedRanking.from_config(self.config) if self.config.ranker != "none" else None
        """The learned ranking of the candidates (:class:`~reeb_torch.ranker.LearnedRanking`,
        ``config.ranker``), or None (``ranker='none'``)."""
        self._features = self.ranker if self.ranker is not None else CandidateFeatures.from_config(self.config)
        self._traces: list[Trace] | None = None  # what trace() collects while it runs
        self._warned_empty = False  # a config that gives no proposals is warned about once
        self._warned_blank = False  # and so is an image without edges
        self._warm_key = _kernel_key(self.config)
        self.compile_s: float = 0.0
        """Seconds the first CPU call spent compiling the kernels (or loading them from
        their cache: :func:`warmup`) before its own work; not in :attr:`stage_times`."""
        self.stage_times: dict[str, float] | None = None
        """Set to ``{}`` to accumulate wall seconds per stage (edges, groups, road,
        regions, scoring, ranker, nms) over calls; ``None`` (default) records
        nothing. The learned ranking's parts are also recorded on their own, within ``ranker``:
        ``ranker.prefilter``, ``ranker.features``, ``ranker.model``, ``ranker.class_head`` and
        ``ranker.refine``.
        Where the two halves of a CPU batch run side by side, each records half its time."""

    @contextmanager
    def _stage(self, name: str, device: torch.device) -> Iterator[None]:
        if self.stage_times is None:
            yield
            return
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        share = getattr(_TIME_SHARE, "share", 1.0)
        yield
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        with _STAGE_LOCK:
            self.stage_times[name] = self.stage_times.get(name, 0.0) + (time.perf_counter() - t0) * share

    def extra_repr(self) -> str:
        c = self.config
        return f"top_k={c.top_k}, scale={c.scale}, use_regions={c.use_regions}, group_cell={c.group_cell}"

    @property
    def classes(self) -> tuple[str, ...] | None:
        """The classes of the ``labels`` and ``class_probs`` of each output (the ranking
        model's class head), or None where there are none (no ranker, or no class head)."""
        return None if self.ranker is None else self.ranker.model.classes

    @property
    def min_side(self) -> int:
        """Smallest image height/width accepted, in input pixels (the smallest window)."""
        return self.config.min_window

    # ------------------------------------------------------------------------------------
    if TYPE_CHECKING:  # nn.Module's __call__ is untyped: type checkers read forward's contract
        def __call__(self, images: ImageBatch) -> list[dict[str, Tensor]]: ...

    @torch.no_grad()
    def forward(self, images: ImageBatch) -> list[dict[str, Tensor]]:
        unchecked: list[int] = []  # float32 CPU images: their values are checked as they are read
        imgs = check_images(images, self.min_side, self.config.front_end, keep_uint8=True, unchecked=unchecked)
        later = set(unchecked)
        check_at = [i if i in later else None for i in range(len(imgs))] if later else None
        on_cpu = imgs[0].device.type == "cpu"
        if on_cpu and self._warm_key not in _WARM:
            self.compile_s += _warm_for(self.config)
        results: list[dict[str, Tensor] | None] = [None] * len(imgs)
        if not on_cpu:
            self._run_sizes(imgs, range(len(imgs)), results, check_at=check_at)
            return results  # type: ignore[return-value]
        # the CPU: each core takes half the images through the whole algorithm (its kernels
        # run serially there), so the two meet once per call, whatever the image sizes; one
        # image has its kernels split between the cores instead
        half = (len(imgs) + 1) // 2

        def run(lo: int, hi: int) -> None:
            for part in range(lo, hi):
                with serially():
                    self._run_sizes(imgs, range(part * half, min(len(imgs), (part + 1) * half)), results, 0.5,
                                    check_at)

        with torch_single_threaded():
            if len(imgs) == 1:
                self._run_sizes(imgs, range(1), results, check_at=check_at)
            else:
                on_two_cores(run, 2)
        return results  # type: ignore[return-value]

    def _run_sizes(self, imgs: list[Tensor], which: range, results: list, share: float = 1.0,
                   check_at: list[int | None] | None = None) -> None:
        """The images ``which`` of ``imgs``, a batch per image size, into ``results``;
        ``share`` of each stage's time is recorded (1/2 where two threads run side by side);
        ``check_at[i]``: image ``i``'s values are yet to be checked (:meth:`_edge_map`)."""
        by_size: dict[tuple, list[int]] = {}
        for i in which:
            by_size.setdefault((tuple(imgs[i].shape), imgs[i].device), []).append(i)
        before = getattr(_TIME_SHARE, "share", 1.0)
        _TIME_SHARE.share = share
        try:
            for idx in by_size.values():
                with _scratch.reusing():  # the batch's large arrays in last batch's memory; results are copies
                    out, _ = self._propose_batch([imgs[i] for i in idx],
                                                 check_at=[check_at[i] for i in idx] if check_at else None)
                for i, r in zip(idx, out):
                    results[i] = r
        finally:
            _TIME_SHARE.share = before

    @torch.no_grad()
    def inspect(self, image: Tensor) -> Inspection:
        """Run on one ``(3, H, W)`` image and keep the intermediate maps (for pictures)."""
        (x,) = check_images([image], self.min_side, self.config.front_end)
        out, extra = self._propose_batch([x], keep=True)
        h, w = x.shape[-2:]
        up = lambda t, mode: F.interpolate(t[None].float(), size=(h, w), mode=mode)[0, 0]  # noqa: E731
        return Inspection(
            boxes=out[0]["boxes"], scores=out[0]["scores"],
            edges=up(extra["edges"], "bilinear"),
            road_mask=up(extra["road"], "nearest") > 0.5,
            regions=extra["regions"], entropy=extra["entropy"][0], share=extra["share"][0],
            num_groups=extra["num_groups"], num_windows=extra["num_windows"], labels=out[0].get("labels"),
        )

    @torch.no_grad()
    def trace(self, image: Tensor) -> tuple[dict[str, Tensor], Trace]:
        """Run on one ``(3, H, W)`` image as :meth:`forward` does and return its output dict
        with what the back end saw on the way (:class:`Trace`: the windows' scores, the region
        cut's candidates and shares, the learned ranking's logits), for diagnostics."""
        self._traces = []
        try:
            out = self([image])[0]
            traced = self._traces[0]
        finally:
            self._traces = None
        return out, traced

    @torch.no_grad()
    def candidates(self, image: Tensor) -> Candidates:
        """The candidates of one ``(3, H, W)`` image before the final ranking and NMS, and
        their features: what :class:`~reeb_torch.ranker.BoxRanker` scores (``reeb fit`` fits
        it on these)."""
        x = self.prepare([image])
        return self.candidates_of(x, self.front_end(x))[0]

    def prepare(self, images: ImageBatch) -> list[Tensor]:
        """``images`` checked as :meth:`forward` checks them (raises as it does): a list of
        ``(3, H, W)`` tensors, float32 in [0, 1] or uint8, for :meth:`front_end`."""
        return check_images(images, self.min_side, self.config.front_end, keep_uint8=True)

    @torch.no_grad()
    def front_end(self, images: list[Tensor]) -> FrontEnd:
        """The work of a batch of equal-sized ``(3, H, W)`` images (as :meth:`prepare` gives
        them) that only :data:`FRONT_END_FIELDS` change: the edge map at the working
        resolution, its groups, (where a score reads it) the road mask, and the score maps
        that keep their integral tables once built. Configs equal in those fields may share
        it (``reeb tune`` computes it once per frame): :meth:`back_end`,
        :meth:`candidates_of`."""
        return self._front_end(images)

    @torch.no_grad()
    def back_end(self, images: list[Tensor], front: FrontEnd) -> list[dict[str, Tensor]]:
        """The rest of the algorithm on :meth:`front_end`'s ``front`` of ``images``: regions,
        windows, scores, the region cut, the learned ranking and NMS; one output
        dict per image, as :meth:`forward` gives (the same boxes, bit for bit)."""
        return self._back_end(images, front)[0]

    @torch.no_grad()
    def candidates_of(self, images: list[Tensor], front: FrontEnd) -> list[Candidates]:
        """:meth:`candidates` of a batch of equal-sized images whose :meth:`front_end` is ``front``."""
        maps = front.maps
        bounds, entropy, share = self.selection.regions(front.working.gray)
        grid = self.selection.window_grid(maps, bounds)
        scores = self.selection.score(maps, grid)
        chosen = self.selection.select(scores, grid, share)
        bi, ni, feats = self._features.features(maps, grid, scores, chosen, share, entropy)
        scale = torch.tensor([maps.fx, maps.fy, maps.fx, maps.fy], device=scores.device)
        boxes = grid.boxes.to(scores.device)[ni] / scale
        counts = torch.bincount(bi, minlength=len(images)).tolist()
        names = self._features.feature_names()
        return [Candidates(b, v.clone(), f, names)
                for b, v, f in zip(boxes.split(counts), scores[bi, ni].split(counts), feats.split(counts))]

    # ------------------------------------------------------------------------------------
    def _propose_batch(self, images: list[Tensor], keep: bool = False,
                       check_at: list[int | None] | None = None) -> tuple[list[dict[str, Tensor]], dict]:
        """The algorithm on a batch of equal-sized ``(3, H, W)`` images, float32 in [0, 1]
        or uint8 (Table 1). With ``keep``, also the intermediate maps for :meth:`inspect`;
        ``check_at``: as in :meth:`_edge_map`."""
        front = self._front_end(images, keep, check_at)
        return self._back_end(images, front, keep)

    def _front_end(self, images: list[Tensor], keep: bool = False,
                   check_at: list[int | None] | None = None) -> FrontEnd:
        """:meth:`front_end`; with ``keep``, the road mask too (for :meth:`inspect`);
        ``check_at``: as in :meth:`_edge_map`."""
        fe, sc = self.config.front_end, self.config.scores
        dev = images[0].device
        needs_road = keep or sc.road_score != "none"
        # Sec. 3.4: Edge_Map = Sobel(Gaussian_Blur(I)), at the working resolution
        with self._stage("edges", dev):
            work = self._edge_map(images, needs_colour=needs_road, check_at=check_at)
        # Sec. 3.7: adjacent edge pixels form edge groups
        with self._stage("groups", dev):
            groups = _groups.connected_groups(work.edges, fe.group_cell)
        # Sec. 3.5: Road_Mask = Generate_Road_Segmentation(I, HSV); skipped when no score reads it
        road = None
        if needs_road:
            with self._stage("road", dev):
                assert work.colour is not None  # needs_colour=needs_road made it
                road = _road.road_mask(work.colour, fe.road_samples, fe.road_band, fe.road_tolerance, fe.seed)
        maps = ScoreMaps(work.edges, groups, (images[0].shape[-2], images[0].shape[-1]), road=road, green=work.green,
                         grey=work.gray[:, 0])
        return FrontEnd(work, maps)

    def _back_end(self, images: list[Tensor], front: FrontEnd,
                  keep: bool = False) -> tuple[list[dict[str, Tensor]], dict]:
        """:meth:`back_end`; with ``keep``, also the maps :meth:`inspect` shows."""
        dev = images[0].device
        work, maps, sel = front.working, front.maps, self.selection
        # one image on the CPU: the groups' tables are built on the other core while this
        # one takes the regions and the integral images, in place of each stage's halves
        beside = len(images) == 1 and sel.scoring.compiled_scoring_may_apply(maps)
        try:
            # Sec. 3.6: Regions = Divide_Image_Into_Regions(I, Camera_Params); eqs. 2 and 9
            with self._stage("regions", dev):
                if beside:
                    maps.start_tables()
                with serially() if beside else nullcontext():
                    bounds, entropy, share = sel.regions(work.gray)
            # Sec. 3.6-3.7: dense sliding windows, scored by eqs. 1, 10-12, cut per region (eq. 9)
            with self._stage("scoring", dev):
                grid = sel.window_grid(maps, bounds)
                scores = sel.score(maps, grid)
                chosen = sel.select(scores, grid, share)
        finally:
            maps.settle()
        trace = None
        if self._traces is not None:  # copies: the next call reuses this memory
            trace = Trace(scores.clone(), grid, chosen.clone(), share.clone())
            self._traces.append(trace)
        # the learned ranking of the candidates (not in the paper; ``ReebConfig.ranker``)
        v_scores = scores
        ranked: list[tuple[Tensor, Tensor, Tensor]] = []  # the ranked candidates' features, for the hints and quota
        class_of = ranked_logits = None
        if self.ranker is not None:
            scores, chosen, class_of, ranked_logits = self._rank(maps, grid, scores, chosen, share, entropy, ranked)
            if trace is not None:
                trace.ranked, trace.kept = scores.clone(), chosen.clone()
        # Sec. 3.8: Final_Proposals = NMS(Sorted_Proposals) (eq. 13)
        windows: list[Tensor] | None = [] if self.classes is not None else None
        with self._stage("nms", dev):
            results = sel.suppress(maps, grid, chosen, scores, windows, class_of,
                                   None if self.ranker is None else self.ranker.class_share)
        if windows is not None:  # which class each proposal looks like (the ranking model's class head)
            assert self.ranker is not None  # classes come from its model
            with self._stage("ranker", dev), self._stage("ranker.class_head", dev):
                for r, probs in zip(results, self.ranker.class_hints(maps, grid, v_scores, share, entropy, windows,
                                                                     ranked[0] if ranked else None, ranked_logits)):
                    r["labels"], r["class_probs"] = probs.argmax(1), probs
        if self.ranker is not None and self.ranker.refines():  # the box refiner (not in the paper)
            with self._stage("ranker", dev), self._stage("ranker.refine", dev):
                results = self.ranker.refine(maps, results)
        empty = [i for i, r in enumerate(results) if len(r["boxes"]) == 0] if not self._warned_empty else []
        if empty:
            self._warn_empty(tuple(images[0].shape[-2:]), grid.count, share, work.edges, empty)
        extra = _kept_maps(maps, bounds, entropy, share, grid.count) if keep else {}
        return results, extra

    def _rank(self, maps: ScoreMaps, grid: WindowGrid, scores: Tensor, chosen: Tensor, share: Tensor,
              entropy: Tensor, ranked: list[tuple[Tensor, Tensor, Tensor]]
              ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """The learned ranking's step: ``(scores, chosen)`` of :meth:`LearnedRanking.rank
        <reeb_torch.ranker.LearnedRanking.rank>`, and with the class quota the hinted class of
        each ranked candidate and the head's logits (:meth:`~reeb_torch.ranker.LearnedRanking.class_map`),
        else None twice; ``ranked`` gets the ranked candidates' features where the hints or
        the quota read them."""
        ranker = self.ranker
        assert ranker is not None
        dev = scores.device
        quota = ranker.class_share is not None
        class_of = ranked_logits = None
        with self._stage("ranker", dev):
            scores, chosen = ranker.rank(maps, grid, scores, chosen, share, entropy,
                                         ranked if self.classes is not None or quota else None,
                                         self._stage if self.stage_times is not None else None)
            if quota and ranked:
                with self._stage("ranker.class_head", dev):
                    class_of, ranked_logits = ranker.class_map(ranked[0], (scores.shape[0], scores.shape[1]))
        return scores, chosen, class_of, ranked_logits

    def _warn_empty(self, size: tuple, windows: int, share: Tensor, edges: Tensor, empty: list[int]) -> None:
        """Warn once per generator (``RuntimeWarning``) that a valid config gave an image no
        proposal, with the likely cause: no window fits, or a zero budget in every region.
        Images of the batch without an edge (``edges[i]`` all 0: a black or constant picture)
        get their own warning, once, and leave the settings' warning for a later image."""
        no_edges = all(not bool(edges[i].amax() > 0) for i in empty)
        with _WARN_LOCK:  # check and set at once: the two halves of a CPU batch run side by side
            if no_edges:
                first, self._warned_blank = not self._warned_blank, True
            else:
                first, self._warned_empty = not self._warned_empty, True
        if not first:
            return
        if no_edges:
            warnings.warn(f"reeb: a {size[1]}×{size[0]} image has no edges (a black or constant picture): "
                          "it gets no proposals; this is warned once", RuntimeWarning, stacklevel=4)
            return
        if windows == 0:
            why = ("no window fits this image (object_templates, min_window, size_ratio, aspect_range, "
                   "ground_band)")
        elif not bool((share.sum(1) > 0).all()):
            why = ("every region's share of the budget is 0 (eq. 9: entropy_bins or entropy_sigma so "
                   "extreme that the shares underflow)")
        else:
            why = "no window was kept (min_edge_score, candidates_per_region, the scores)"
        warnings.warn(f"reeb: the settings gave a {size[1]}×{size[0]} image no proposals: {why}; "
                      "this is warned once", RuntimeWarning, stacklevel=4)

    # -- the stages' settings ---------------------------------------------------------------
    def _edge_map(self, images: list[Tensor], needs_colour: bool,
                  check_at: list[int | None] | None = None) -> Working:
        """Sec. 3.4 on the batch: the working-resolution grey image (the compiled front end
        where it applies, else resize and grey as tensor ops), the green-pixel counts, the
        edge map.

        ``check_at[j]`` not ``None``: image ``j`` (image ``check_at[j]`` of the caller's
        batch, as the error names it) is float32 whose values are not yet checked; the
        compiled front end counts the values outside [0, 1] as it reads them (a float image
        read once, not twice), else :func:`check_range` does."""
        fe, sc = self.config.front_end, self.config.scores
        colour: Tensor | None = None
        gray: Tensor | None = None
        green: Tensor | None = None
        want_green = sc.vegetation_score != "none"
        pending = [(j, i) for j, i in enumerate(check_at or ()) if i is not None]
        if not needs_colour:
            outside: list[int] | None = [] if pending else None
            front = _edges.working_gray(images, fe.scale, with_green=want_green, outside=outside)
            if front is not None:
                gray, green = front
                pending = [(j, i) for j, i in pending if outside[j] != 0]  # type: ignore[index]
        for j, i in pending:  # values outside [0, 1] (raises), or not looked at yet
            check_range(images[j], f"image {i}")
        if gray is None:
            colour = _edges.working_images(images, fe.scale)
            gray = _edges.to_gray(colour)
            green = _scoring.count_integral(_edges.green_mask(colour)) if want_green else None
        edges = _edges.edge_map(gray, fe.blur_sigma, fe.edge_threshold, fe.remove_isolated, fe.thin_edges)
        return Working(gray, edges, colour, green)


def _kept_maps(maps: ScoreMaps, bounds: Tensor, entropy: Tensor, share: Tensor, num_windows: int) -> dict:
    """What :meth:`ProposalGenerator.inspect` shows besides the proposals: the maps, and the region strips
    in input pixels."""
    fx, h_in = maps.fx, maps.input_size[0]
    regions = torch.stack([bounds[:, 0] / fx, torch.zeros(len(bounds)),
                           bounds[:, 1] / fx, torch.full((len(bounds),), float(h_in))], 1).float()
    return dict(edges=maps.edges, road=maps.road, entropy=entropy, share=share, regions=regions,
                num_groups=len(maps.groups), num_windows=num_windows)


def propose(images: ImageBatch, config: ReebConfig | None = None, **overrides: object) -> list[dict[str, Tensor]]:
    """Functional form of :class:`ProposalGenerator`: ``propose(images, config)``."""
    return ProposalGenerator(config, **overrides)(images)


def _warm_for(config: ReebConfig) -> float:
    """:func:`warmup` of one config before its first call; a config the synthetic picture
    does not fit (a very large ``min_window``) compiles on its first image instead."""
    t0 = time.perf_counter()
    try:
        return warmup(config)
    except ValueError:
        _WARM.add(_kernel_key(config))
        return time.perf_counter() - t0


def _kernel_key(config: ReebConfig) -> tuple:
    """What decides which kernels (and which of their typed versions) a config runs: its
    switches (every bool and string field) and the few numbers that pick a path. Configs
    that differ only in other numbers (``top_k``, ``alpha``, ...) share one warm-up, so a
    sweep over settings does not pay it per trial."""
    key = [(f.name, getattr(config, f.name)) for f in dataclasses.fields(config)
           if isinstance(getattr(config, f.name), (bool, str))]
    key += [("sqrt_shadow", config.shadow_power == 0.5),
            ("front_end", 0 < config.scale < 1), ("ground", config.ground_band is None)]
    return tuple(key)


def warmup(*configs: ReebConfig, quiet: bool = False) -> float:
    """Compile the CPU kernels that ``configs`` (default: ``ReebConfig()``) use, or load
    them from their on-disk cache, by running each on a small synthetic picture as uint8
    and as float input; returns the seconds it took.

    The first call of a :class:`ProposalGenerator` on the CPU does this itself (timed
    apart: :attr:`ProposalGenerator.compile_s`); call it (or ``reeb warmup``) ahead of time,
    e.g. at install, to pay the one-time compile there. While the kernels are not yet
    cached it says so on stderr, unless ``quiet``, and a second Python process compiles
    the kernels the run reaches last meanwhile (numba compiles on one core per process;
    ``$REEB_TORCH_WARM_HELPER`` set: one process only). The cache is per user and survives a
    reinstall of the same version (:mod:`reeb_torch.stages._kernel_cache`; ``$REEB_TORCH_CACHE_DIR``).
    Python's garbage collector is paused while it runs, with one collection at the end
    (:func:`reeb_torch._warm.gc_paused`)."""
    t0 = time.perf_counter()
    x = warm_picture()
    with Notice(quiet) as notice:
        helper = start_helper() if notice.first else None  # compiles the last kernels meanwhile
        try:
            with gc_paused():  # and one collection after: not in the first call's time
                for cfg in configs or (ReebConfig(),):
                    _WARM.add(_kernel_key(cfg))  # before the run: its own forward must not warm up again
                    gen = ProposalGenerator(cfg)
                    gen._warned_empty = True  # the synthetic picture may keep no window: not the user's images
                    gen([x])
                    gen(torch.stack([x, x.flip(-1)]).float().div_(255.0))
        finally:
            stop_helper(helper)
    return time.perf_counter() - t0
