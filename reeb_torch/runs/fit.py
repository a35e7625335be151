"""``reeb fit``: the command's work around :mod:`reeb_torch.eval.fit` (load the frames, take
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
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from ..config import ReebConfig
from ..eval import fit as F
from ..eval import fit_cv
from ..eval.common import folder_blocks
from ..eval.metrics import compare_recall
from ..eval.tune import FrameCache, bootstrap_interval, fold_blocks, objective
from ..ranker import dropped_columns

if TYPE_CHECKING:
    from ..ranker import BoxRanker

__all__ = ["run_fit", "frames_digest", "FitOutputs", "FEW_FRAMES"]

FEW_FRAMES = 20
"""Below this many frames, a fit from scratch prints a hint to fine-tune instead (``--init``)."""


def _bar(total: int, desc: str, quiet: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=True if quiet else None, file=sys.stderr, dynamic_ncols=True)


def _iterate(desc: str, quiet: bool):
    """A progress-bar wrapper for the engine's loops (``progress=``)."""
    def wrap(items):
        items = list(items)
        with _bar(len(items), desc, quiet) as bar:
            for it in items:
                yield it
                bar.update()

    return wrap


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


def _hint_report(frames: F.FitFrames, hinted: list) -> tuple[list[str], dict[str, Any]]:
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
    line = (f"class hints (cross-validated; the hint of each found object's best proposal): "
            f"{100 * right / len(pairs):.1f} % right of {len(pairs)} ({shown})")
    return [line], {"right": right, "found": len(pairs), "per_class": per_class}


def _shipped_hits(cache: FrameCache, cfg: ReebConfig, k: int, iou: float) -> list | None:
    """The shipped model's hits on the frames, or None where it cannot rank this config's features."""
    from ..ranker import RankerWeightsError

    try:
        return cache.hits(cfg.replace(ranker="kitti"), range(len(cache.frames)), k, iou)
    except RankerWeightsError:
        return None


def _other_folder_hits(cache: FrameCache, cfg: ReebConfig, samples: Sequence[F.Sample], opts: F.FitOptions,
                       k: int, iou: float, quiet: bool, scratch: Path) -> list | None:
    """Per frame, the objects the generator finds with a model fitted (or fine-tuned) on the
    other folders only, a block per folder: how a model holds on frames unlike those it saw;
    None for frames of one folder."""
    from ..eval.metrics import object_hits

    blocks = [idx for _, idx in folder_blocks(cache.frames.folders)]
    if not blocks:
        return None
    outputs = fit_cv.held_out_outputs(cache, cfg, samples, opts, blocks, progress=_iterate("other folders", quiet),
                                 scratch=scratch)
    return object_hits([o["boxes"] for o in outputs], cache.frames.gts, k, iou)


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

    def __init__(self, out: str | os.PathLike) -> None:
        from .common import UsageProblem

        text = os.fspath(out)
        if not text.strip():
            raise UsageProblem("-o/--out is empty: give the weights file to write, e.g. -o ranker.safetensors")
        self.weights = Path(os.path.expanduser(text))
        self.config = self.weights.with_suffix(".json")
        if self.weights.suffix.lower() == ".json" or self.config == self.weights:
            raise UsageProblem(f"{self.weights}: the config written beside the weights is {self.config}, the same "
                               f"file; name the weights apart, e.g. -o {self.weights.with_suffix('.safetensors')}")
        problem = _unwritable(self.weights) or _unwritable(self.config)
        if problem:
            raise UsageProblem(problem)
        self.scratch = self.weights.parent / f"{_hidden(self.weights)}.fit"
        self._locks: list = []

    def __enter__(self) -> "FitOutputs":
        from .output_files import OutputError, stale_temp_files
        from .output_lock import lock_output
        from .common import UsageProblem

        try:
            for path in (self.weights, self.config):
                self._locks.append(lock_output(path))
            # what a killed fit on this output left: its scratch folder, its temporary files
            shutil.rmtree(self.scratch, ignore_errors=True)
            for stale in stale_temp_files(self.weights) + stale_temp_files(self.config):
                stale.unlink(missing_ok=True)
            self.scratch.mkdir()
        except (OSError, OutputError) as e:
            self._release()
            raise UsageProblem(" ".join(str(e).split())) from None
        return self

    def __exit__(self, *exc: object) -> None:
        shutil.rmtree(self.scratch, ignore_errors=True)
        self._release()

    def _release(self) -> None:
        for lock in self._locks:
            lock.release()
        self._locks = []

    def write(self, model: BoxRanker, provenance: dict[str, Any], cfg: ReebConfig) -> None:
        """The weights, then the config, each renamed into place; a one-line
        :class:`~reeb_torch.runs.common.Failure` (exit code 1) when one cannot be written (the
        files keep what they held) or the weights are not finite (nothing is written)."""
        from ..ranker import SHIPPED, RankerWeightsError, save_ranker
        from ..io import replace_file
        from .common import Failure

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
    from .output_files import hidden_stem

    return hidden_stem(path)


def _unwritable(path: Path) -> str | None:
    """Why ``path`` cannot be written as an output file (its folder made where missing), or None."""
    if path.is_dir():
        return f"{path}: is a folder; give a file name such as {path / 'ranker.safetensors'}"
    parent = path.parent
    above = next((q for q in (parent, *parent.parents) if q.exists()), None)
    if above is not None and not above.is_dir():
        return f"{path}: cannot write, {above} is a file, not a folder"
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"{path}: cannot write, cannot make the folder {parent} ({e.strerror or e})"
    if path.exists() and not os.access(path, os.W_OK):
        return f"{path}: cannot write, the file is read-only"
    try:
        fd, probe = tempfile.mkstemp(prefix=f"{_hidden(path)}.", suffix=".probe", dir=parent)
    except OSError as e:
        return f"{path}: cannot write to the folder {parent} ({e.strerror or e})"
    os.close(fd)
    os.unlink(probe)
    return None


def run_fit(roots: Sequence[str], out: str, cfg: ReebConfig, opts: F.FitOptions, folds: int, k: int = 2000,
            iou: float = 0.7, limit: int | None = None, quiet: bool = False,
            command: str = "", whole_drives: bool = False) -> dict[str, Any]:
    """The whole of ``reeb fit``; returns the record (also in the weights' metadata).

    ``whole_drives``: a held-out block's training frames leave out every frame of its drives
    (ids naming a drive, as KITTI tracking's), not only those within 2 frames of it: an
    estimate for drives the model never saw.

    ``cfg`` is the config the ranking is fitted for (its candidates; its ``ranker`` is
    replaced by the new weights); it is compared with ``cfg.training_free()`` and, where it
    can rank these features, the shipped ``kitti`` model, on the same frames.

    The output is checked and locked before any work (:class:`FitOutputs`).

    Raises:
        ValueError: no labels, fewer frames than folds, nothing to fit on; a ``--init`` model that
            cannot be read or reads other features (:class:`~reeb_torch.ranker.RankerWeightsError`).
        UsageProblem: ``out`` cannot be written, or another fit holds it (exit code 2).
        Failure: the weights cannot be written, or are not finite (exit code 1).
    """
    import warnings

    outputs = FitOutputs(out)
    with outputs, warnings.catch_warnings():
        # the shipped model's row and a --init model run on this config by design: the
        # generator's warning that they were fitted with other settings is no news here
        warnings.filterwarnings("ignore", message=r"reeb: the ranker .* was fitted with other settings",
                                category=UserWarning)
        return _run_fit(roots, outputs, cfg, opts, folds, k, iou, limit, quiet, command, whole_drives)


def _run_fit(roots: Sequence[str], outputs: FitOutputs, cfg: ReebConfig, opts: F.FitOptions, folds: int, k: int,
             iou: float, limit: int | None, quiet: bool, command: str, whole_drives: bool) -> dict[str, Any]:
    from ..ranker import frame_hash, load_ranker, seen_hashes

    t0 = time.monotonic()
    if opts.init:
        load_ranker(opts.init)  # a file that is no model is refused before the frames are read
    frames = F.load_fit_frames(roots, limit=limit)
    fold_blocks(len(frames), folds)  # refuse fewer frames than folds before any work
    cache = FrameCache(frames)
    base = cfg.training_free()
    names = cache.candidates(cfg.unranked(), 0).feature_names
    if opts.init:
        F.initial_model(opts.init, names)  # a model that cannot be tuned here fails before any work
    dropped_columns(names, opts.drop_features)  # and so does an unknown column
    samples = F.frame_samples(cache, cfg, opts, progress=_iterate("candidates", quiet))
    gap = len(frames) if whole_drives else 2  # drive frames within ``gap`` of a held-out block stay out
    cv = fit_cv.cross_validate(cache, cfg, base, samples, opts, folds, k, iou, gap, progress=_iterate("folds", quiet),
                               scratch=outputs.scratch)
    model = F.fit_ranker(samples, names, opts, frames.classes, fit_cv.kept_rows(cache, cfg, opts, range(len(frames))))
    fitted = "fine-tuned (cross-validated)" if opts.init else "fitted (cross-validated)"
    rows = {"training-free": cv.base_hits, fitted: cv.ranked_hits}
    table, record = _report(frames, rows, cv.base_hits)  # kept in the weights: the same for the same frames
    hint_lines, hint_record = _hint_report(frames, cv.hinted)
    shown = dict(rows)
    other = _other_folder_hits(cache, cfg, samples, opts, k, iou, quiet, outputs.scratch)
    other_row = f"{'fine-tuned' if opts.init else 'fitted'} on other folders"
    if other is not None:
        shown[other_row] = other
    if opts.init and opts.init != "kitti":
        start = cfg.replace(ranker=opts.init)
        shown[f"{Path(opts.init).name} as it is"] = cache.hits(start, range(len(frames)), k, iou)
    shipped = _shipped_hits(cache, cfg, k, iou)
    if shipped is not None:
        shown["shipped kitti model"] = shipped
    if len(shown) > len(rows):
        table = _report(frames, shown, cv.base_hits)[0]
    provenance: dict[str, Any] = {
        "data": [os.path.basename(os.path.normpath(r)) for r in roots], "frames": len(frames),
        "objects": sum(len(g) for g in frames.gts), "frames_digest": frames_digest(frames),
        "frame_hashes": {f"{os.path.basename(os.path.normpath(f))}/{i}": frame_hash(im)
                         for f, i, im in zip(frames.folders, frames.ids, frames.images)},
        "options": _options_record(opts), "folds": folds, "k": k, "iou": iou, "command": command,
        "cross_validated": record,
    }
    if whole_drives:
        provenance["whole_drives"] = True
    if opts.init:
        was = model.meta.get("provenance", {})
        provenance["init"] = {"model": opts.init, "data": was.get("data"), "frames_digest": was.get("frames_digest"),
                              "frame_hashes": seen_hashes(was)}
    if hint_record:
        provenance["class_hints"] = hint_record
    outputs.write(model, provenance, cfg)
    load_ranker(str(outputs.weights), model.feature_names)  # what it wrote reads back
    apart = ("no frame of a held-out block's drives on the training side" if whole_drives
             else "no neighbouring frames of one drive on both sides")
    head = (f"{len(frames)} frames, {provenance['objects']} objects; {folds} folds of blocks of frames ({apart}); "
            f"recall at {k} proposals, IoU {iou}, "
            "95 % frame-bootstrap intervals; "
            f"{time.monotonic() - t0:.0f} s")
    note = []
    if other is not None and objective(other, frames.labels) < objective(cv.base_hits, frames.labels):
        note.append(f"  ({other_row}: each folder ranked by a model that saw only the others finds fewer objects "
                    "than training-free: a model may not carry to frames unlike those it was fitted on)")
    if shipped is not None:
        note += _seen_note("the shipped model", load_ranker("kitti"), frames, provenance["frames_digest"],
                           "its row")
    if not opts.init and len(frames) < FEW_FRAMES:
        note.append(f"  ({len(frames)} frames: with 5 or 10 frames of a drive, fine-tuning a model fitted elsewhere "
                    "(--init kitti) beat a fit from scratch on the dev folders; see reeb fit in docs/cli.md)")
    if opts.init:
        note += _seen_note(f"the model fine-tuned, {opts.init},", load_ranker(opts.init), frames,
                           provenance["frames_digest"], f"the {fitted} row")
    text = "\n".join([head] + table + note + hint_lines
                     + [outputs.hint()])
    return {"provenance": provenance, "text": text, "weights": str(outputs.weights), "config": str(outputs.config)}


def _seen_note(who: str, model: BoxRanker, frames: F.FitFrames, digest: str, row: str) -> list[str]:
    """A line where ``model`` was fitted on some or all of ``frames`` (the same pictures, by
    :func:`~reeb_torch.ranker.fitted_frames`, or the same frame list by its digest, for files
    without frame hashes): there its recall is in-sample."""
    from ..ranker import fitted_frames

    seen = sum(s is not None for s in fitted_frames(model, frames.images))
    if seen == len(frames) or model.meta.get("provenance", {}).get("frames_digest") == digest:
        return [f"  ({who} was fitted on these frames: {row} is no estimate)"]
    if seen:
        return [f"  ({who} was fitted on {seen} of these {len(frames)} frames: {row} is in-sample there)"]
    return []


def _options_record(opts: F.FitOptions) -> dict[str, Any]:
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
