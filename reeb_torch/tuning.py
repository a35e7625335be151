"""``reeb tune``'s engine: search ReebConfig settings on labelled frames with Optuna, and
estimate how the tuned settings do on new frames by nested cross-validation over frames.

* :func:`load_frames` reads KITTI-format folders (images and labels) once;
  :class:`FrameCache` keeps each frame's edge map, groups and road mask (the work that only
  :data:`reeb_torch.generator.FRONT_END_FIELDS` change) so a trial that searches ranking
  settings (geometry, score powers, budgets, NMS) costs only regions, scoring and NMS.
* :func:`default_space` / :func:`load_space`: the search space, checked against ReebConfig.
* :func:`fold_blocks` splits the frames into K contiguous blocks; :func:`held_out` scores,
  on each block, a config chosen without it beside a base config (the loop that ``reeb
  tune``'s and ``reeb fit``'s cross-validations share).
* :func:`cross_validate`: for each block, a study on the other K−1 blocks picks settings
  that are then scored on the held-out block (nested: the block never informs its own
  settings). The held-out hits of all blocks give the estimate, with a frame-bootstrap
  interval, beside the base config's on the same frames.
* :func:`tune`: one study on all frames, for the settings to use.

Optuna is the optional extra ``tune`` (``pip install reeb-torch[tune]``), imported when a
study starts.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence, cast

import numpy as np
import torch
from torch import Tensor

from ._memory import trim_heap
from .config import ReebConfig
from .datasets.folders import load_folders
from .generator import FRONT_END_FIELDS, Candidates, FrontEnd, ProposalGenerator
from .metrics.recall import RecallInterval, bootstrap_recalls, object_hits, recall_interval
from .ranker import SHIPPED, refine_features

__all__ = ["Frames", "FrameCache", "Param", "default_space", "load_space", "Estimate", "CrossValidation",
           "load_frames", "photometric_jitter", "score_config", "objective", "bootstrap_interval", "fold_blocks",
           "held_out", "cross_validate", "tune", "StudyOptions"]


# -- frames ------------------------------------------------------------------------------------

@dataclass
class Frames:
    """Labelled frames held in memory: ``images`` uint8 ``Tensor[3, H, W]``, ``gts``
    ``Tensor[N_i, 4]`` boxes, ``labels`` ``int64 Tensor[N_i]`` indices into ``classes``,
    ``ids`` and ``folders`` per frame."""

    images: list[Tensor]
    gts: list[Tensor]
    labels: list[Tensor]
    classes: tuple[str, ...]
    ids: list[str]
    folders: list[str]

    def __len__(self) -> int:
        return len(self.images)


def load_frames(roots: Sequence[str | os.PathLike], limit: int | None = None) -> Frames:
    """Read the frames of KITTI-format folders (:func:`reeb_torch.datasets.folders.load_folders`).

    Raises:
        ValueError: no folder, a folder without labels, or no labelled object at all.
    """

    items, classes = load_folders(roots, limit=limit)
    frames = Frames([it["image"] for it in items], [it["boxes"] for it in items],
                    [it["labels"] for it in items], tuple(classes), [str(it["image_id"]) for it in items],
                    [it["folder"] for it in items])
    if sum(len(g) for g in frames.gts) == 0:
        raise ValueError(f"no labelled object of the classes {', '.join(classes)} in "
                         f"{' '.join(map(str, roots))}: recall is undefined")
    return frames


def _weights_stamp(ranker: str) -> tuple[int, int] | None:
    """The modification time and size of the weights file ``ranker`` names; None for none, a
    shipped name, or a file that cannot be read (the generator then says what is wrong)."""

    if ranker in ("none", *SHIPPED):
        return None
    try:
        st = os.stat(os.path.expanduser(ranker))
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


class FrameCache:
    """Proposals of many configs on the same frames, computing each frame's front end (edges,
    groups, road mask) once per setting of :data:`~reeb_torch.generator.FRONT_END_FIELDS` (the
    latest one is kept). The boxes are those of ``ProposalGenerator(cfg)(image)``, bit for bit."""

    def __init__(self, frames: Frames, budget: int | None = None) -> None:
        self.frames = frames
        self.budget = budget
        """Bytes of front ends kept (the first frames' ones; the last one computed is kept
        too); None: every frame's (fast, but memory grows with the frames)."""
        self._key: tuple | None = None
        self._front: dict[int | tuple, FrontEnd] = {}
        self._bytes = 0
        self._last: tuple[int | tuple, FrontEnd] | None = None
        self.front_computed = 0
        """How many frames' front ends were computed (for tests and the summary)."""
        self._generators: dict[tuple, ProposalGenerator] = {}

    def _generator(self, cfg: ReebConfig) -> ProposalGenerator:
        """The generator of ``cfg``, kept for the last few configs: its ranking keeps the window
        plans per image size (the base config is scored again and again). A weights file
        written again under the same path is a new generator (its model is read once)."""
        key = (cfg, _weights_stamp(cfg.ranker))
        if key not in self._generators:
            if len(self._generators) >= 4:
                self._generators.pop(next(iter(self._generators)))
            self._generators[key] = ProposalGenerator(cfg)
        return self._generators[key]

    def _front_of(self, cfg: ReebConfig, i: int, mirrored: bool = False,
                  photometric: tuple[float, float] | None = None
                  ) -> tuple[ProposalGenerator, list[Tensor], FrontEnd]:
        """The generator of ``cfg``, frame ``i`` (flipped left to right with ``mirrored``; its
        contrast and brightness changed by ``photometric``, :func:`photometric_jitter`) as its
        input, and that image's front end (each variant cached apart from the frame's own)."""
        key = tuple(getattr(cfg, f) for f in FRONT_END_FIELDS)
        if key != self._key:
            self._key, self._front, self._bytes, self._last = key, {}, 0, None
        gen = self._generator(cfg)
        image = self.frames.images[i]
        if mirrored:
            image = image.flip(-1)
        if photometric is not None:
            image = photometric_jitter(image, *photometric)
        img = gen.prepare([image])
        slot: int | tuple = (i, mirrored, photometric) if mirrored or photometric is not None else i
        if slot in self._front:
            return gen, img, self._front[slot]
        if self._last is not None and self._last[0] == slot:
            return gen, img, self._last[1]
        with torch.no_grad():
            front = gen.front_end(img)
        self.front_computed += 1
        size = _nbytes(front) if self.budget is not None else 0
        if self.budget is None or self._bytes + size <= self.budget:
            self._front[slot] = front
            self._bytes += size
        self._last = (slot, front)
        return gen, img, front

    def outputs(self, cfg: ReebConfig, indices: Sequence[int]) -> list[dict[str, Tensor]]:
        """``ProposalGenerator(cfg)``'s output dict (``boxes``, ``scores``, and ``labels``,
        ``class_probs`` where the ranker hints classes) for each of the frames ``indices``."""
        out = []
        with torch.no_grad():
            for i in indices:
                gen, img, front = self._front_of(cfg, i)
                results = gen.back_end(img, front)
                out.append({k: v.detach().cpu() for k, v in results[0].items()})
        return out

    def proposals(self, cfg: ReebConfig, indices: Sequence[int]) -> list[Tensor]:
        """Ranked boxes ``Tensor[P_i, 4]`` (``P_i <= cfg.top_k``) for the frames ``indices``."""
        return [o["boxes"] for o in self.outputs(cfg, indices)]

    def candidates(self, cfg: ReebConfig, i: int, mirrored: bool = False,
                   photometric: tuple[float, float] | None = None) -> Candidates:
        """Frame ``i``'s candidates and their features under ``cfg``
        (:meth:`reeb_torch.ProposalGenerator.candidates`); with ``mirrored``, those of the frame
        flipped left to right (boxes in the flipped image's coordinates); with ``photometric``
        ``(contrast, brightness)``, those of the frame so changed (:func:`photometric_jitter`)."""
        with torch.no_grad():
            gen, img, front = self._front_of(cfg, i, mirrored, photometric)
            return gen.candidates_of(img, front)[0]

    def refine_features(self, cfg: ReebConfig, i: int, boxes: Tensor, mirrored: bool = False,
                        photometric: tuple[float, float] | None = None) -> Tensor:
        """The box refiner's features (:func:`reeb_torch.ranker.refine_features`) of ``boxes``
        (``float [K, 4]`` input pixels) in frame ``i`` (as :meth:`candidates` takes it):
        ``float32 [K, R]``."""

        with torch.no_grad():
            _, _, front = self._front_of(cfg, i, mirrored, photometric)
            maps = front.maps
            to_work = torch.tensor([maps.fx, maps.fy, maps.fx, maps.fy], device=maps.edges.device)
            bi = torch.zeros(len(boxes), dtype=torch.long, device=maps.edges.device)
            return refine_features(maps.integral("edges"), maps.integral("grey"), boxes.to(to_work.device) * to_work,
                                   bi, cfg.horizon).cpu()

    def hits(self, cfg: ReebConfig, indices: Sequence[int], k: int, iou: float) -> list[Tensor]:
        """Per frame of ``indices``, ``bool Tensor[N_i]``: objects the top ``k`` boxes find at ``iou``."""
        return object_hits(self.proposals(cfg, indices), [self.frames.gts[i] for i in indices], k, iou)


def _nbytes(obj: Any, seen: set | None = None) -> int:
    """Bytes of the tensors ``obj`` holds (in its fields, lists, tuples and dicts), each once."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, Tensor):
        storage = obj.untyped_storage()
        if ("storage", storage.data_ptr()) in seen:
            return 0
        seen.add(("storage", storage.data_ptr()))  # type: ignore[arg-type]
        return storage.nbytes()
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(_nbytes(v, seen) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_nbytes(v, seen) for v in obj)
    if dataclasses.is_dataclass(obj) or hasattr(obj, "__dict__"):
        fields = vars(obj) if hasattr(obj, "__dict__") else {f.name: getattr(obj, f.name)
                                                             for f in dataclasses.fields(obj)}
        return sum(_nbytes(v, seen) for v in fields.values())
    if hasattr(obj, "__slots__"):
        return sum(_nbytes(getattr(obj, n, None), seen) for n in obj.__slots__)
    return 0


def photometric_jitter(image: Tensor, contrast: float, brightness: float) -> Tensor:
    """``uint8 [3, H, W]`` ``image`` with its contrast scaled by ``contrast`` about its mean
    and ``brightness`` (in grey levels) added, rounded and clipped to 0–255."""
    x = image.float()
    x = (x - x.mean()) * contrast + x.mean() + brightness
    return x.round().clamp(0, 255).to(torch.uint8)


def objective(hits: Sequence[Tensor], labels: Sequence[Tensor], balanced: bool = False) -> float:
    """Recall in [0, 1]: found / objects (micro), or with ``balanced`` the mean over the classes
    present of each class's recall. NaN when there is no object."""
    h = torch.cat([x.reshape(-1).float() for x in hits]) if hits else torch.zeros(0)
    if h.numel() == 0:
        return float("nan")
    if not balanced:
        return float(h.mean())
    lab = torch.cat([x.reshape(-1) for x in labels])
    return float(torch.stack([h[lab == c].mean() for c in lab.unique()]).mean())


Estimate = RecallInterval
"""A recall (fraction) with its frame-bootstrap interval: :class:`~reeb_torch.metrics.recall.RecallInterval`
(micro, or the mean of the class recalls with ``balanced``)."""


def bootstrap_interval(hits: Sequence[Tensor], labels: Sequence[Tensor], balanced: bool = False,
                       level: float = 0.95, samples: int = 4000, seed: int = 0) -> Estimate:
    """:func:`objective` with the frame-bootstrap percentile interval of
    :func:`~reeb_torch.metrics.recall.recall_interval` (frames with no object are left out).
    Micro recall is that function's estimate, interval and all, so one set of hits gives one
    interval in ``reeb fit``, ``reeb tune`` and Table 3; ``balanced`` takes the mean of the
    class recalls on the same draws (:func:`~reeb_torch.metrics.recall.bootstrap_recalls`).

    Raises:
        ValueError: ``level`` outside (0, 1), ``samples < 1``, or no object at all.
    """
    micro = recall_interval(hits, level, samples, seed)
    if not balanced:
        return micro
    keep = [i for i, h in enumerate(hits) if h.numel()]
    hs, ls = [hits[i] for i in keep], [labels[i] for i in keep]
    classes = sorted({int(c) for lab in ls for c in lab.reshape(-1).tolist()})
    found = torch.tensor([[int(h[lab == c].sum()) for c in classes] for h, lab in zip(hs, ls)], dtype=torch.float64)
    count = torch.tensor([[int((lab == c).sum()) for c in classes] for lab in ls], dtype=torch.float64)
    vals = bootstrap_recalls(found, count, samples, seed, balanced=True)
    low, high = torch.quantile(vals, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=torch.float64)).tolist()
    return Estimate(objective(hs, ls, True), low, high, level, micro.num_objects, micro.num_images)


def score_config(cache: FrameCache, cfg: ReebConfig, indices: Sequence[int] | None = None, k: int = 2000,
                 iou: float = 0.7, balanced: bool = False) -> tuple[Estimate, list[Tensor]]:
    """``cfg``'s recall at ``k`` / ``iou`` on the frames ``indices`` (default all), with its
    interval, and the hits per frame (for :func:`reeb_torch.metrics.recall.compare_recall`)."""
    idx = list(range(len(cache.frames))) if indices is None else list(indices)
    hits = cache.hits(cfg, idx, k, iou)
    return bootstrap_interval(hits, [cache.frames.labels[i] for i in idx], balanced), hits


# -- the search space ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Param:
    """One searched field: ``kind`` ``"float"`` / ``"int"`` in ``[low, high]`` (``step``,
    ``log`` as Optuna's ``suggest_float`` / ``suggest_int``), or ``"categorical"`` over ``choices``."""

    kind: str
    low: float | None = None
    high: float | None = None
    step: float | None = None
    log: bool = False
    choices: tuple = ()

    def _range(self) -> tuple[float, float]:
        """``(low, high)`` of a numeric parameter."""
        if self.low is None or self.high is None:
            raise ValueError(f"a {self.kind!r} parameter needs low and high")
        return self.low, self.high

    def suggest(self, trial: Any, name: str) -> Any:
        if self.kind == "categorical":
            return trial.suggest_categorical(name, list(self.choices))
        lo, hi = self._range()
        if self.kind == "float":
            return trial.suggest_float(name, lo, hi, step=self.step, log=self.log)
        return trial.suggest_int(name, int(lo), int(hi), step=int(self.step or 1), log=self.log)

    def contains(self, value: Any) -> bool:
        if self.kind == "categorical":
            return value in self.choices
        lo, hi = self._range()
        return isinstance(value, (int, float)) and lo <= value <= hi

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"type": self.kind}
        if self.kind == "categorical":
            d["choices"] = list(self.choices)
        else:
            d.update(low=self.low, high=self.high)
            if self.step is not None:
                d["step"] = self.step
            if self.log:
                d["log"] = True
        return d


def default_space() -> dict[str, Param]:
    """The settings that matter, around the default: the camera geometry, the score terms'
    powers and tolerance, the candidate budget and NMS."""
    return {
        "horizon": Param("float", 0.40, 0.56),
        "camera_height_m": Param("float", 1.2, 2.2),
        "kappa": Param("float", 1.2, 2.0),
        "ground_log_sigma": Param("float", 0.15, 0.6),
        "shadow_power": Param("float", 0.1, 1.5),
        "vegetation_power": Param("int", 1, 10),
        "candidates_per_region": Param("int", 4000, 16000, step=2000),
        "nms_iou": Param("float", 0.65, 0.85),
    }


def _param(name: str, spec: Any, hints: dict[str, Any]) -> Param:
    """One entry of a space file, checked: a known field, a known kind, a range ReebConfig takes."""
    where = f"search space field {name!r}"
    if not isinstance(spec, dict) or spec.get("type") not in ("float", "int", "categorical"):
        raise ValueError(f"{where}: expected {{\"type\": \"float\" | \"int\" | \"categorical\", ...}}, got {spec!r}")
    extra = set(spec) - {"type", "low", "high", "step", "log", "choices"}
    if extra:
        raise ValueError(f"{where}: unknown key(s) {', '.join(sorted(extra))}")
    kind = spec["type"]
    if kind == "categorical":
        choices = spec.get("choices")
        if not isinstance(choices, list) or not choices:
            raise ValueError(f"{where}: a categorical entry needs a non-empty list 'choices'")
        p = Param(kind, choices=tuple(tuple(c) if isinstance(c, list) else c for c in choices))
        values = list(p.choices)
    else:
        lo, hi = spec.get("low"), spec.get("high")
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (lo, hi))
        if not numbers or not cast(float, lo) <= cast(float, hi):
            raise ValueError(f"{where}: needs numbers low <= high, got low={lo!r}, high={hi!r}")
        lo, hi = cast(float, lo), cast(float, hi)
        if kind == "int" and not (float(lo).is_integer() and float(hi).is_integer()):
            raise ValueError(f"{where}: an int entry needs whole low and high, got {lo}, {hi}")
        p = Param(kind, lo, hi, spec.get("step"), bool(spec.get("log", False)))
        values = [int(lo), int(hi)] if kind == "int" else [float(lo), float(hi)]
    for v in values:
        try:
            ReebConfig(**{name: v})
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: the value {v!r} is not a valid setting ({e})") from None
    return p


def load_space(spec: str | os.PathLike | dict | None) -> dict[str, Param]:
    """The search space from a JSON file or dict ``{field: {"type": "float", "low": a, "high": b}, ...}``
    (``"int"`` likewise, with an optional ``"step"``; ``"log": true``; ``"categorical"`` with
    ``"choices"``); ``None`` gives :func:`default_space`.

    Raises:
        ValueError: an unknown ReebConfig field (named), a malformed entry, a bound ReebConfig
            refuses, an empty space, or a file that is not JSON.
    """
    if spec is None:
        return default_space()
    if not isinstance(spec, dict):
        try:
            with open(spec, encoding="utf-8") as f:
                spec = json.load(f)
        except json.JSONDecodeError as e:
            raise ValueError(f"{spec}: not valid JSON ({e})") from None
    if not isinstance(spec, dict) or not spec:
        raise ValueError("the search space must be a non-empty JSON object of ReebConfig fields")
    hints = {f.name: f.type for f in dataclasses.fields(ReebConfig)}
    unknown = sorted(set(spec) - set(hints))
    if unknown:
        raise ValueError(f"unknown ReebConfig field(s) in the search space: {', '.join(unknown)}")
    return {name: _param(name, s, hints) for name, s in spec.items()}


# -- studies -------------------------------------------------------------------------------------

@dataclass
class StudyOptions:
    """How each study runs: ``trials`` per study, Optuna ``storage`` URL (``sqlite:///x.db``;
    ``None`` in memory), ``resume`` (continue the studies stored there), a wall-clock
    ``deadline`` (``time.monotonic()`` value; ``None``: none), the objective (``k``, ``iou``,
    ``balanced``) and ``on_trial`` (called after each finished trial, e.g. a progress bar)."""

    trials: int = 50
    seed: int = 0
    storage: str | None = None
    resume: bool = False
    deadline: float | None = None
    k: int = 2000
    iou: float = 0.7
    balanced: bool = False
    on_trial: Callable[[], None] | None = None
    name: str = "reeb-tune"
    """Prefix of the study names (:func:`study_prefix` makes one per data and settings)."""


def study_prefix(frames: Frames, base: ReebConfig, space: dict[str, Param], folds: int, opts: StudyOptions) -> str:
    """A study name that changes with anything that would make stored trials incomparable."""
    blob = json.dumps([frames.ids, frames.folders, base.fingerprint(), {k: p.to_dict() for k, p in space.items()},
                       folds, opts.k, opts.iou, opts.balanced, opts.seed], sort_keys=True, default=str)
    return "reeb-tune-" + hashlib.sha256(blob.encode()).hexdigest()[:12]


def _optuna() -> Any:
    try:
        import optuna
    except ImportError:
        raise ImportError("reeb tune needs Optuna: pip install 'reeb-torch[tune]'") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def _open_study(name: str, opts: StudyOptions, seed: int) -> Any:
    optuna = _optuna()
    done = 0
    if opts.resume and opts.storage:
        try:
            old = optuna.load_study(study_name=name, storage=opts.storage)
            done = len(old.trials)
        except KeyError:
            done = 0
    # the sampler's seed moves on with the trials already stored, so a resumed study does not
    # replay the first trials' settings
    sampler = optuna.samplers.TPESampler(seed=seed + 7919 * done, n_startup_trials=min(10, max(1, opts.trials // 2)))
    try:
        return optuna.create_study(study_name=name, storage=opts.storage, direction="maximize", sampler=sampler,
                                   load_if_exists=opts.resume)
    except optuna.exceptions.DuplicatedStudyError:
        raise ValueError(f"{opts.storage} already holds the study {name}: pass --resume to continue it, "
                         "or another --storage") from None


def _completed(study: Any) -> int:
    from optuna.trial import TrialState

    return sum(t.state == TrialState.COMPLETE for t in study.trials)


def run_study(cache: FrameCache, base: ReebConfig, space: dict[str, Param], indices: Sequence[int],
              opts: StudyOptions, name: str, seed: int, studies_left: int = 1) -> tuple[dict[str, Any], Any]:
    """Search ``space`` over ``base`` on the frames ``indices``; the first trial is the base
    config itself (where it lies in the space), so the best found is never worse on these frames.

    Returns ``(best params, study)``; ``{}`` (the base) when no trial finished in time.
    """
    study = _open_study(name, opts, seed)
    labels = [cache.frames.labels[i] for i in indices]

    def run(trial: Any) -> float:
        params = {n: p.suggest(trial, n) for n, p in space.items()}
        try:
            cfg = base.replace(**params)
        except (TypeError, ValueError) as e:  # a joint condition of ReebConfig
            trial.set_user_attr("invalid", str(e))
            return 0.0
        return objective(cache.hits(cfg, indices, opts.k, opts.iou), labels, opts.balanced)

    if not study.trials:
        start = {n: getattr(base, n) for n, p in space.items() if p.contains(getattr(base, n))}
        if len(start) == len(space):
            study.enqueue_trial(start)
    left = opts.trials - _completed(study)
    timeout = None
    if opts.deadline is not None:
        timeout = (opts.deadline - time.monotonic()) / max(1, studies_left)
    if left > 0 and (timeout is None or timeout > 0):
        on_trial = opts.on_trial
        callbacks = [lambda s, t: on_trial()] if on_trial is not None else []
        study.optimize(run, n_trials=left, timeout=timeout, callbacks=callbacks, catch=())
    try:
        return dict(study.best_params), study
    except ValueError:  # no completed trial
        return {}, study


@dataclass
class CrossValidation:
    """Nested cross-validation over contiguous blocks of frames.

    Attributes:
        folds: frame indices of each held-out block.
        best: per block, the settings the study on the other blocks chose.
        tuned, base: the held-out estimate of the tuned settings and of the base config on the
            same frames (:class:`Estimate`); tuned_hits, base_hits: their hits per frame.
        per_fold: per block, ``(tuned recall, base recall)`` on it.
    """

    folds: list[list[int]]
    best: list[dict[str, Any]]
    tuned: Estimate
    base: Estimate
    tuned_hits: list[Tensor] = field(repr=False)
    base_hits: list[Tensor] = field(repr=False)
    per_fold: list[tuple[float, float]]


def fold_blocks(n: int, folds: int) -> list[list[int]]:
    """``folds`` contiguous blocks of ``range(n)``, sizes differing by at most one.

    Raises:
        ValueError: ``folds < 2`` or fewer frames than folds.
    """
    if folds < 2:
        raise ValueError(f"cross-validation needs at least 2 folds, got {folds}")
    if n < folds:
        raise ValueError(f"{n} labelled frames cannot make {folds} folds: give more frames or fewer --folds")
    return [b.tolist() for b in np.array_split(np.arange(n), folds)]


@dataclass
class HeldOut:
    """:func:`held_out`'s hits, per frame in the order of the blocks' frames.

    Attributes:
        hits: ``bool [N_i]`` per frame: the objects the config chosen without its block finds.
        base_hits: the same for the base config.
        per_fold: per block, ``(chosen recall, base recall)`` on it (:func:`objective`).
    """

    hits: list[Tensor] = field(repr=False)
    base_hits: list[Tensor] = field(repr=False)
    per_fold: list[tuple[float, float]]


def held_out(cache: FrameCache, blocks: Sequence[Sequence[int]], chosen: Callable[[int], ReebConfig],
             base: ReebConfig, k: int = 2000, iou: float = 0.7, balanced: bool = False,
             each: Callable[[list[int], list[dict[str, Tensor]]], None] | None = None,
             progress: Callable | None = None, chunk: int = 64) -> HeldOut:
    """For each block ``f`` of frame indices, in turn: ``chosen(f)``, a config picked without
    the block (settings tuned, or a model fitted, on the other blocks), run on the block; its
    hits of the top ``k`` at ``iou`` paired with ``base``'s on the same objects.
    ``each(frames, outputs)``, if given, sees the output dicts of the chosen config, a part of
    a block at a time (``chunk`` frames, in order: a block's outputs are never all held);
    ``progress`` wraps the iteration over the blocks (e.g. a progress bar)."""
    frames = cache.frames
    hits: list[Tensor] = []
    base_hits: list[Tensor] = []
    per_fold = []
    for f in progress(range(len(blocks))) if progress else range(len(blocks)):
        block = list(blocks[f])
        cfg = chosen(f)
        found: list[Tensor] = []
        base_found: list[Tensor] = []
        for s in range(0, len(block), chunk):
            part = block[s: s + chunk]
            outputs = cache.outputs(cfg, part)
            found += object_hits([o["boxes"] for o in outputs], [frames.gts[i] for i in part], k, iou)
            base_found += cache.hits(base, part, k, iou)
            if each is not None:
                each(part, outputs)
            trim_heap()
        labels = [frames.labels[i] for i in block]
        per_fold.append((objective(found, labels, balanced), objective(base_found, labels, balanced)))
        hits += found
        base_hits += base_found
    return HeldOut(hits, base_hits, per_fold)


def cross_validate(cache: FrameCache, base: ReebConfig, space: dict[str, Param], folds: int,
                   opts: StudyOptions, studies_after: int = 1) -> CrossValidation:
    """For each of ``folds`` blocks: a study on the others, scored on the block (see the module;
    :func:`held_out`). ``studies_after``: studies still to run after these (they share the
    time budget)."""
    blocks = fold_blocks(len(cache.frames), folds)
    best: list[dict[str, Any]] = []

    def tuned(f: int) -> ReebConfig:
        train = [i for b in blocks[:f] + blocks[f + 1:] for i in b]
        params, _ = run_study(cache, base, space, train, opts, f"{opts.name}-fold{f}", opts.seed + 1 + f,
                              studies_left=folds - f + studies_after)
        best.append(params)
        return base.replace(**params)

    scored = held_out(cache, blocks, tuned, base, opts.k, opts.iou, opts.balanced)
    t_hits, b_hits, per_fold = scored.hits, scored.base_hits, scored.per_fold
    order = [i for b in blocks for i in b]
    labels = [cache.frames.labels[i] for i in order]
    return CrossValidation(blocks, best, bootstrap_interval(t_hits, labels, opts.balanced),
                           bootstrap_interval(b_hits, labels, opts.balanced), t_hits, b_hits, per_fold)


def tune(cache: FrameCache, base: ReebConfig, space: dict[str, Param], opts: StudyOptions) -> tuple[ReebConfig, Any]:
    """One study on all frames: ``(the tuned config, the study)``."""
    params, study = run_study(cache, base, space, list(range(len(cache.frames))), opts, f"{opts.name}-all",
                              opts.seed)
    return base.replace(**params), study
