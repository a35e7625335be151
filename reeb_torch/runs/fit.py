"""``reeb fit``: the command's work around :mod:`reeb_torch.ranker.frames` (load the frames, take
their candidates, cross-validate, fit on all of them, print, write the weights and a config
that ``reeb propose --config`` reads).

It writes as ``reeb propose`` does (:class:`FitOutputs`): the output is checked before any
work, a lock beside it keeps a second fit off it, and each file goes through a temporary file
renamed into place, so a failed or killed fit leaves the files that were there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import sys
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from tqdm import tqdm

from ..config import ReebConfig
from ..datasets.folders import folder_blocks
from ..io import replace_file
from ..metrics.recall import compare_recall, object_hits
from ..ranker import (
    SHIPPED,
    RankerWeightsError,
    cv as fit_cv,
    dropped_columns,
    fit as RF,
    fitted_frames,
    frame_hash,
    frames as F,
    load_ranker,
    save_ranker,
    seen_hashes,
)
from ..ranker.store import Checkpoints, RowStore, StoredFrames, StoreError
from ..tuning import FrameCache, bootstrap_interval, fold_blocks, objective
from .claim import check_files, claim
from .common import Failure, UsageProblem, ray_engine
from .fit_ray import ray_rows
from .output_files import hidden_stem

if TYPE_CHECKING:
    from ..ranker import BoxRanker

__all__ = ["run_fit", "frames_digest", "FitOutputs", "FEW_FRAMES"]

FEW_FRAMES = 20
"""Below this many frames, a fit from scratch prints a hint to fine-tune instead (``--init``)."""


def _bar(total: int, desc: str, quiet: bool) -> Any:
    return tqdm(total=total, desc=desc, disable=True if quiet else None, file=sys.stderr, dynamic_ncols=True)


ESTIMATE_AFTER = 8
"""A long stage prints its estimated time once this many of its items are done."""


def _iterate(desc: str, quiet: bool):
    """A progress-bar wrapper for the engine's loops (``progress=``); a stage of many items
    says, once its first :data:`ESTIMATE_AFTER` are done, how long the whole should take."""
    def wrap(items):
        items = list(items)
        t0 = time.monotonic()
        with _bar(len(items), desc, quiet) as bar:
            for n, it in enumerate(items, 1):
                yield it
                bar.update()
                if n == ESTIMATE_AFTER and len(items) > 4 * ESTIMATE_AFTER and not quiet:
                    each = (time.monotonic() - t0) / n
                    bar.write(f"reeb fit: {desc}: about {_duration(each * len(items))} for {len(items)} "
                              f"({each:.2f} s each, from the first {n})", file=sys.stderr)

    return wrap


def _duration(seconds: float) -> str:
    """``seconds`` as a person reads it: ``40 s``, ``12 min``, ``3.5 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def frames_digest(frames: F.FitFrames) -> str:
    """A short digest of which frames a model was fitted on (folder names and ids)."""
    text = "\n".join(sorted(f"{f}/{i}" for f, i in zip(frames.folders, frames.ids)))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _row(name: str, hits: list, ref: list | None, frames: F.FitFrames, idx: Sequence[int]) -> dict[str, Any]:
    """Recall (with its interval), per class, and the pairing with ``ref`` on the frames ``idx``."""
    h, lab = [hits[i] for i in idx], [frames.labels[i] for i in idx]
    est = bootstrap_interval(h, lab)
    per_class = {}
    for c, cname in enumerate(frames.classes):
        n = sum(int((x == c).sum()) for x in lab)
        if n:
            per_class[cname] = 100 * sum(int(y[x == c].sum()) for y, x in zip(h, lab)) / n
    row = {"name": name, "recall": 100 * est.recall, "low": 100 * est.low, "high": 100 * est.high,
           "objects": est.num_objects, "per_class": per_class}
    if ref is not None:
        row["paired"] = dataclasses.asdict(compare_recall([ref[i] for i in idx], h))
    return row


def _fmt(row: dict[str, Any]) -> str:
    classes = ", ".join(f"{c} {v:.1f}" for c, v in row["per_class"].items())
    paired = ""
    if "paired" in row:
        p = row["paired"]
        paired = f"; against training-free +{p['gained']} / -{p['lost']}, p {p['p_value']:.2g}"
    return (f"  {row['name']:<28} {row['recall']:5.1f} % ({row['low']:.1f}-{row['high']:.1f}; {classes})"
            f"{paired}")


def _report(frames: F.FitFrames, rows: dict[str, list], ref: list) -> tuple[list[str], dict[str, Any]]:
    """The table of each setting's recall over all frames and per folder."""
    groups = [("all frames", list(range(len(frames)))), *folder_blocks(frames.folders)]
    lines: list[str] = []
    record: dict[str, Any] = {}
    for title, idx in groups:
        lines.append(f"{title} ({len(idx)} frames):")
        record[title] = []
        for name, hits in rows.items():
            row = _row(name, hits, None if hits is ref else ref, frames, idx)
            record[title].append(row)
            lines.append(_fmt(row))
    return lines, record


def _hint_report(frames: F.FitFrames, hinted: list, how: str = "cross-validated") -> tuple[list[str], dict[str, Any]]:
    """How often the cross-validated models' class hints name the class of the objects their
    proposals find (the hint of each object's best proposal), overall and per class."""
    pairs = [(c, h) for lab, hint in zip(frames.labels, hinted) for c, h in zip(lab.tolist(), hint.tolist()) if h >= 0]
    if not pairs:
        return [], {}
    per_class = {}
    for c, name in enumerate(frames.classes):
        hints = [h for t, h in pairs if t == c]
        if hints:
            per_class[name] = {"right": sum(h == c for h in hints), "found": len(hints),
                               "taken_for": {frames.classes[o]: hints.count(o) for o in sorted(set(hints)) if o != c}}
    right = sum(t == h for t, h in pairs)
    shown = ", ".join(f"{n} {v['right']}/{v['found']}" for n, v in per_class.items())
    line = (f"class hints ({how}; the hint of each found object's best proposal): "
            f"{100 * right / len(pairs):.1f} % right of {len(pairs)} ({shown})")
    return [line], {"right": right, "found": len(pairs), "per_class": per_class}


def _shipped_hits(cache: FrameCache, cfg: ReebConfig, k: int, iou: float) -> list | None:
    """The shipped model's hits on the frames, or None where it cannot rank this config's features."""

    try:
        return cache.hits(cfg.replace(ranker="kitti"), range(len(cache.frames)), k, iou)
    except RankerWeightsError:
        return None


def _other_folder_hits(cache: FrameCache, cfg: ReebConfig, samples: Sequence[RF.Sample] | StoredFrames,
                       opts: RF.FitOptions, k: int, iou: float, quiet: bool, scratch: Path,
                       keep: Path | None = None) -> list | None:
    """Per frame, the objects the generator finds with a model fitted (or fine-tuned) on the
    other folders only, a block per folder: how a model holds on frames unlike those it saw;
    None for frames of one folder."""

    blocks = [idx for _, idx in folder_blocks(cache.frames.folders)]
    if not blocks:
        return None
    gts = cache.frames.gts
    return fit_cv.held_out_outputs(cache, cfg, samples, opts, blocks, progress=_iterate("other folders", quiet),
                                   scratch=scratch, keep=keep,
                                   reduce=lambda i, o: object_hits([o["boxes"]], [gts[i]], k, iou)[0])


class FitOutputs:
    """The two files ``reeb fit -o OUT`` writes: the weights (``OUT``) and, beside them, the
    config that ``reeb propose --config`` reads (``OUT`` with the suffix ``.json``, naming the
    weights by their file name, so it reads from any folder).

    Made before any work: raises :class:`~reeb_torch.runs.common.UsageProblem` (exit code 2)
    when ``OUT`` is empty, a folder, a ``.json`` name (the config would be the weights), in a
    folder that cannot be made or written, or read-only. As a context manager it holds the
    lock of both files (:func:`~reeb_torch.runs.output_lock.lock_output`: a second fit on them
    exits 2 at once) and a scratch folder beside them for the held-out models (the process's
    default temporary folder while it is held), removed at the end or, after a kill, by the
    next fit on the same output (with the temporary files a killed write left).
    """

    def __init__(self, out: str | os.PathLike, overwrite: bool = False) -> None:
        text = os.fspath(out)
        if not text.strip():
            raise UsageProblem("-o/--out is empty: give the weights file to write, e.g. -o ranker.safetensors")
        self.weights = Path(os.path.expanduser(text))
        self.config = self.weights.with_suffix(".json")
        if self.weights.suffix.lower() == ".json" or self.config == self.weights:
            raise UsageProblem(f"{self.weights}: the config written beside the weights is {self.config}, the same "
                               f"file; name the weights apart, e.g. -o {self.weights.with_suffix('.safetensors')}")
        check_files([self.weights, self.config], overwrite, example="ranker.safetensors")  # claimed on entering
        self.scratch = self.weights.parent / f"{_hidden(self.weights)}.fit"
        self.store = self.weights.parent / f"{_hidden(self.weights)}.store"
        """The fit's row store, held-out models and training states: kept after a kill (the
        same command goes on from it), removed once the weights are written."""
        self._release: Callable[[], None] = lambda: None

    def __enter__(self) -> "FitOutputs":
        self._release = claim([self.weights, self.config], hold=False, clear=True)  # and what a kill left
        try:
            shutil.rmtree(self.scratch, ignore_errors=True)  # what a killed fit on this output left
            self.scratch.mkdir()
        except OSError as e:
            self._release()
            raise UsageProblem(" ".join(str(e).split())) from None
        return self

    def __exit__(self, *exc: object) -> None:
        shutil.rmtree(self.scratch, ignore_errors=True)
        self._release()

    def write(self, model: BoxRanker, provenance: dict[str, Any], cfg: ReebConfig) -> None:
        """The weights, then the config, each renamed into place; a one-line
        :class:`~reeb_torch.runs.common.Failure` (exit code 1) when one cannot be written (the
        files keep what they held) or the weights are not finite (nothing is written)."""

        name = self.weights.name
        ranker = f"./{name}" if name in SHIPPED or name == "none" else name  # not a shipped name
        text = json.dumps({**_changed(cfg), "ranker": ranker}, indent=2) + "\n"
        try:
            save_ranker(model, self.weights, provenance, cfg.to_dict())
            replace_file(self.config, text.encode("utf-8"))
        except RankerWeightsError as e:
            raise Failure(f"{self.weights}: not written, the fit gave weights that cannot rank "
                          f"({str(e).split(': ', 1)[-1]})") from None
        except OSError as e:
            raise Failure(f"{e.filename or self.weights}: cannot write ({e.strerror or e}); the file that was "
                          "there is unchanged") from None

    def hint(self) -> str:
        """The closing line: what was written and the command that uses it."""
        return (f"wrote {self.weights} and {self.config} "
                f"(reeb propose --config {shlex.quote(str(self.config))})")


def _hidden(path: Path) -> str:
    return hidden_stem(path)


def run_fit(roots: Sequence[str], out: str, cfg: ReebConfig, opts: RF.FitOptions, folds: int, k: int = 2000,
            iou: float = 0.7, limit: int | None = None, quiet: bool = False,
            command: str = "", whole_drives: bool = False, val: Sequence[str] = (),
            engine: tuple[str | None, int, float | None] | None = None, overwrite: bool = False) -> dict[str, Any]:
    """The whole of ``reeb fit``; returns the record (also in the weights' metadata).

    ``val``: labelled folders the ranking is scored on instead of a cross-validation (one fit,
    one pass over them: the estimate for data sets where ``folds`` fits would take long;
    ``folds`` and ``whole_drives`` then do not apply).

    Memory does not grow with the frames: the images are read when used, each frame's rows
    are appended to a store beside ``out`` and trained from by minibatch
    (:func:`~reeb_torch.ranker.frames.row_store`), and the training states are kept after each
    epoch, so a killed fit, started again with the same arguments, goes on from where it was
    and ends with the weights of one never stopped.

    ``engine``: ``(address, actors, cpus_per_actor)``: each frame's rows are made on Ray Data
    (:func:`~reeb_torch.runs.fit_ray.ray_rows`: a local Ray instance, or the cluster at
    ``address``); None: in this process. The rows are the same either way.

    ``whole_drives``: a held-out block's training frames leave out every frame of its drives
    (ids naming a drive, as KITTI tracking's), not only those within 2 frames of it: an
    estimate for drives the model never saw.

    ``cfg`` is the config the ranking is fitted for (its candidates; its ``ranker`` is
    replaced by the new weights); it is compared with ``cfg.training_free()`` and, where it
    can rank these features, the shipped ``kitti`` model, on the same frames.

    The output is checked and locked before any work (:class:`FitOutputs`); weights or a
    config already there are replaced only with ``overwrite``.

    Raises:
        ValueError: no labels, fewer frames than folds, nothing to fit on; a ``--init`` model that
            cannot be read or reads other features (:class:`~reeb_torch.ranker.RankerWeightsError`).
        UsageProblem: ``out`` cannot be written, or another fit holds it (exit code 2).
        Failure: the weights cannot be written, or are not finite (exit code 1).
    """

    outputs = FitOutputs(out, overwrite)
    with outputs, warnings.catch_warnings():
        # the shipped model's row and a --init model run on this config by design: the
        # generator's warning that they were fitted with other settings is no news here
        warnings.filterwarnings("ignore", message=r"reeb: the ranker .* was fitted with other settings",
                                category=UserWarning)
        try:
            return _run_fit(roots, outputs, cfg, opts, folds, k, iou, limit, quiet, command, whole_drives, val,
                            engine)
        except StoreError as e:  # a full disk under the row store: the weights there stay

            raise Failure(f"{e}; {outputs.weights} is unchanged") from None


def _run_fit(roots: Sequence[str], outputs: FitOutputs, cfg: ReebConfig, opts: RF.FitOptions, folds: int, k: int,
             iou: float, limit: int | None, quiet: bool, command: str, whole_drives: bool,
             val: Sequence[str] = (), engine: tuple[str | None, int, float | None] | None = None) -> dict[str, Any]:
    t0 = time.monotonic()
    if opts.init:
        load_ranker(opts.init)  # a file that is no model is refused before the frames are read
    frames = F.load_fit_frames(roots, limit=limit, lazy=True)
    scored = F.load_fit_frames(val, lazy=True) if val else None  # read before any work: its problems first
    if scored is None:
        fold_blocks(len(frames), folds)  # refuse fewer frames than folds before any work
    cache = FrameCache(frames, budget=FRONT_END_BUDGET)
    names = cache.candidates(cfg.unranked(), 0).feature_names
    if opts.init:
        RF.initial_model(opts.init, names)  # a model that cannot be tuned here fails before any work
    dropped_columns(names, opts.drop_features)  # and so does an unknown column
    store = _open_store(outputs, cache, cfg, opts, quiet)
    clock = _Stages(t0)
    clock("frames")
    samples = _rows(cache, cfg, opts, store, engine, quiet)
    clock("rows")
    est = None
    if scored is None:
        est = _cross_validated(cache, cfg, samples, opts, folds, k, iou, whole_drives, quiet, outputs, clock)
    states = Checkpoints(outputs.store / "final", [dataclasses.asdict(opts), len(frames)])
    model = RF.fit_ranker(samples, names, opts, frames.classes, fit_cv.kept_rows(cache, cfg, opts, range(len(frames))),
                         checkpoints=states.slot)
    clock("fit")
    if scored is not None:
        est = _validated(scored, model, cfg, opts, k, iou, outputs, quiet, clock)
    assert est is not None
    provenance: dict[str, Any] = {
        "data": [os.path.basename(os.path.normpath(r)) for r in roots], "frames": len(frames),
        "objects": sum(len(g) for g in frames.gts), "frames_digest": frames_digest(frames),
        "frame_hashes": {f"{os.path.basename(os.path.normpath(f))}/{i}": frame_hash(im)
                         for f, i, im in zip(frames.folders, frames.ids, frames.images)},
        "options": _options_record(opts), "k": k, "iou": iou, "command": command,
    }
    if scored is None:
        provenance.update(folds=folds, cross_validated=est.record)
    else:
        provenance["validated"] = {"folders": [str(v) for v in val], **est.record}
    if whole_drives:
        provenance["whole_drives"] = True
    if opts.init:
        was = model.meta.get("provenance", {})
        provenance["init"] = {"model": opts.init, "data": was.get("data"), "frames_digest": was.get("frames_digest"),
                              "frame_hashes": seen_hashes(was)}
    if est.hint_record:
        provenance["class_hints"] = est.hint_record
    outputs.write(model, provenance, cfg)
    load_ranker(str(outputs.weights), model.feature_names)  # what it wrote reads back
    store.remove()  # the weights are written: nothing to go on from
    if scored is None:
        apart = ("no frame of a held-out block's drives on the training side" if whole_drives
                 else "no neighbouring frames of one drive on both sides")
        how = f"{len(frames)} frames, {provenance['objects']} objects; {folds} folds of blocks of frames ({apart})"
    else:
        how = (f"fitted on {len(frames)} frames ({provenance['objects']} objects), scored on the {len(scored)} "
               f"frames of --val ({sum(len(g) for g in scored.gts)} objects)")
    head = f"{how}; recall at {k} proposals, IoU {iou}, 95 % frame-bootstrap intervals; {time.monotonic() - t0:.0f} s"
    note = est.notes
    shown_frames = est.frames
    digest = frames_digest(shown_frames)
    if est.shipped:
        note += _seen_note("the shipped model", load_ranker("kitti"), shown_frames, digest, "its row")
    if not opts.init and len(frames) < FEW_FRAMES:
        note.append(f"  ({len(frames)} frames: with 5 or 10 frames of a drive, fine-tuning a model fitted elsewhere "
                    "(--init kitti) beat a fit from scratch on the dev folders; see reeb fit in docs/cli.md)")
    if opts.init:
        note += _seen_note(f"the model fine-tuned, {opts.init},", load_ranker(opts.init), shown_frames, digest,
                           f"the {est.fitted} row")
    text = "\n".join([head] + est.table + note + est.hint_lines + [clock.line(), outputs.hint()])
    return {"provenance": provenance, "text": text, "weights": str(outputs.weights), "config": str(outputs.config),
            "stages_s": clock.seconds}


@dataclasses.dataclass
class _Estimate:
    """How the fitted ranking does on frames it was not fitted on: the table's lines and
    record, the frames it scored, the name of the fitted row, notes, the class hints' lines
    and record, and whether the shipped model has a row."""

    table: list[str]
    record: dict[str, Any]
    frames: F.FitFrames
    fitted: str
    notes: list[str]
    hint_lines: list[str]
    hint_record: dict[str, Any]
    shipped: bool


def _other_rows(cache: FrameCache, cfg: ReebConfig, opts: RF.FitOptions, k: int, iou: float,
                clock: _Stages) -> dict[str, list]:
    """The rows beside the fitted one on ``cache``'s frames: the ``--init`` model as it is (not
    the shipped one) and the shipped model (where it can rank these features)."""
    out: dict[str, list] = {}
    if opts.init and opts.init != "kitti":
        start = cfg.replace(ranker=opts.init)
        out[f"{Path(opts.init).name} as it is"] = cache.hits(start, range(len(cache.frames)), k, iou)
    shipped = _shipped_hits(cache, cfg, k, iou)
    clock("shipped model")
    if shipped is not None:
        out["shipped kitti model"] = shipped
    return out


def _cross_validated(cache: FrameCache, cfg: ReebConfig, samples: Sequence[RF.Sample] | StoredFrames,
                     opts: RF.FitOptions, folds: int, k: int, iou: float, whole_drives: bool, quiet: bool,
                     outputs: FitOutputs, clock: _Stages) -> _Estimate:
    """``reeb fit``'s estimate by cross-validation over blocks of its frames, and the models
    fitted on the other folders (one block per folder)."""
    frames = cache.frames
    assert isinstance(frames, F.FitFrames)
    base = cfg.training_free()
    gap = len(frames) if whole_drives else 2  # drive frames within ``gap`` of a held-out block stay out
    cv = fit_cv.cross_validate(cache, cfg, base, samples, opts, folds, k, iou, gap, progress=_iterate("folds", quiet),
                               scratch=outputs.scratch, keep=outputs.store)
    clock("cross-validation")
    fitted = "fine-tuned (cross-validated)" if opts.init else "fitted (cross-validated)"
    rows = {"training-free": cv.base_hits, fitted: cv.ranked_hits}
    table, record = _report(frames, rows, cv.base_hits)  # kept in the weights: the same for the same frames
    hint_lines, hint_record = _hint_report(frames, cv.hinted)  # type: ignore[arg-type]
    shown = dict(rows)
    other = _other_folder_hits(cache, cfg, samples, opts, k, iou, quiet, outputs.scratch, outputs.store)
    clock("other folders" if other is not None else None)
    other_row = f"{'fine-tuned' if opts.init else 'fitted'} on other folders"
    if other is not None:
        shown[other_row] = other
    beside = _other_rows(cache, cfg, opts, k, iou, clock)
    shown.update(beside)
    if len(shown) > len(rows):
        table = _report(frames, shown, cv.base_hits)[0]
    notes = []
    if other is not None and objective(other, frames.labels) < objective(cv.base_hits, frames.labels):
        notes.append(f"  ({other_row}: each folder ranked by a model that saw only the others finds fewer objects "
                     "than training-free: a model may not carry to frames unlike those it was fitted on)")
    return _Estimate(table, record, frames, fitted, notes, hint_lines, hint_record,  # type: ignore[arg-type]
                     "shipped kitti model" in beside)


def _validated(scored: F.FitFrames, model: BoxRanker, cfg: ReebConfig, opts: RF.FitOptions, k: int, iou: float,
               outputs: FitOutputs, quiet: bool, clock: _Stages) -> _Estimate:
    """``reeb fit --val``'s estimate: the fitted model on the ``--val`` frames (which it was
    not fitted on) beside training-free and the shipped model, one pass over them."""

    cache = FrameCache(scored, budget=FRONT_END_BUDGET)
    weights = save_ranker(model, outputs.store / "validated.safetensors")
    every = range(len(scored))

    with _bar(2, "--val frames", quiet) as bar:
        base = cache.hits(cfg.training_free(), every, k, iou)
        bar.update()
        found = cache.outputs(cfg.replace(ranker=str(weights)), every)
        bar.update()
    clock("validation")
    ranked = object_hits([o["boxes"] for o in found], scored.gts, k, iou)
    fitted = "fine-tuned (on DIRS)" if opts.init else "fitted (on DIRS)"
    rows = {"training-free": base, fitted: ranked}
    table, record = _report(scored, rows, base)
    hint_lines, hint_record = _hint_report(scored, fit_cv.hinted_classes(found, scored.gts, k, iou), "on --val")
    del found
    beside = _other_rows(cache, cfg, opts, k, iou, clock)
    if beside:
        table = _report(scored, {**rows, **beside}, base)[0]
    return _Estimate(table, record, scored, fitted, [], hint_lines, hint_record,  # type: ignore[arg-type]
                     "shipped kitti model" in beside)


class _Stages:
    """Wall seconds of each stage of a fit, from ``t0`` (``clock(name)`` ends the stage)."""

    def __init__(self, t0: float) -> None:
        self.last, self.seconds = t0, {}  # type: float, dict[str, float]

    def __call__(self, name: str | None) -> None:
        """End the stage ``name`` (None: one that did not run, not shown)."""
        now = time.monotonic()
        if name is not None:
            self.seconds[name] = round(now - self.last, 2)
        self.last = now

    def line(self) -> str:
        return "stages: " + ", ".join(f"{n} {v:.0f} s" for n, v in self.seconds.items())


FRONT_END_BUDGET = 0
"""Bytes of the frames' front ends (edges, groups, road mask) a fit keeps between its passes
over the frames (the last one read is kept too); the others are computed again when read. A
front end kept holds its tables and the memory its scoring left in use, so a fit keeps none:
its memory then does not grow with the frames (docs/results.md, "Fits at scale")."""


def _rows(cache: FrameCache, cfg: ReebConfig, opts: F.FitOptions, store: RowStore,
          engine: tuple[str | None, int, float | None] | None, quiet: bool) -> StoredFrames:
    """Every frame's training rows in ``store``: those it lacks made here
    (:func:`~reeb_torch.ranker.frames.frame_samples`) or on Ray (``engine``)."""
    if engine is None:
        out = F.frame_samples(cache, cfg, opts, progress=_iterate("candidates", quiet), store=store)
        assert isinstance(out, StoredFrames)
        return out

    actors, cpus = ray_engine(engine, quiet)
    total = len(cache.frames) - len(store)

    def counted(items):
        with _bar(total, "candidates (ray)", quiet) as bar:
            for it in items:
                yield it
                bar.update()

    try:
        ray_rows(store, cache.frames, cfg, opts, actors, cpus, progress=counted)
    except StoreError:
        raise
    except Exception as e:  # noqa: BLE001 - a failed Ray job: the frames finished so far stay in the store
        raise Failure(f"the Ray job failed: {' '.join(str(e).split())[:2000]}") from None
    return store.frames()


def _open_store(outputs: FitOutputs, cache: FrameCache, cfg: ReebConfig, opts: RF.FitOptions,
                quiet: bool) -> RowStore:
    """The fit's row store beside its output (:func:`~reeb_torch.ranker.frames.row_store`), with a
    line where a killed fit's rows are gone on from or a store made otherwise is made again."""

    try:
        store = F.row_store(outputs.store, cache, cfg, opts)
    except StoreError as e:
        raise Failure(str(e)) from None
    if not quiet:
        if store.rebuilt:
            print(f"reeb fit: the row store {outputs.store} was {store.rebuilt}: made again", file=sys.stderr)
        elif len(store):
            print(f"reeb fit: going on from {outputs.store} ({len(store)} of {len(cache.frames)} frames' rows "
                  "made before)", file=sys.stderr)
    return store


def _seen_note(who: str, model: BoxRanker, frames: F.FitFrames, digest: str, row: str) -> list[str]:
    """A line where ``model`` was fitted on some or all of ``frames`` (the same pictures, by
    :func:`~reeb_torch.ranker.fitted_frames`, or the same frame list by its digest, for files
    without frame hashes): there its recall is in-sample."""

    seen = sum(s is not None for s in fitted_frames(model, frames.images))
    if seen == len(frames) or model.meta.get("provenance", {}).get("frames_digest") == digest:
        return [f"  ({who} was fitted on these frames: {row} is no estimate)"]
    if seen:
        return [f"  ({who} was fitted on {seen} of these {len(frames)} frames: {row} is in-sample there)"]
    return []


def _options_record(opts: RF.FitOptions) -> dict[str, Any]:
    """The fit options kept in the weights' provenance; ``mirror``, ``jitter``,
    ``drop_features``, ``hard_negatives`` and the box refiner's options only where they are on
    (a fit without them records what it always did)."""
    record = dataclasses.asdict(opts)
    for name in ("mirror", "jitter", "drop_features", "hard_negatives"):
        if not record[name]:
            del record[name]
    if opts.refine_hidden is None:
        for name in [n for n in record if n.startswith("refine_")]:
            del record[name]
    return record


def _changed(cfg: ReebConfig) -> dict[str, Any]:
    """The fields of ``cfg`` that differ from the package default, but the ranker."""
    default = ReebConfig().to_dict()
    return {k: v for k, v in cfg.to_dict().items() if default[k] != v and k != "ranker"}
