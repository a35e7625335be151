"""``reeb tune``: the command's work around :mod:`reeb_torch.tuning` (load, search,
cross-validate, print, write the tuned config, its record and the plots)."""

from __future__ import annotations

import io
import json
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from tqdm import tqdm

from .. import tuning as T
from ..config import ReebConfig
from ..io import replace_file
from ..metrics.recall import compare_recall
from .claim import claim_files

__all__ = ["run_tune", "run_score", "plot_study"]


def _progress(total: int, quiet: bool) -> Any:
    """The trials' tqdm bar on stderr (silent with ``quiet``), as ``reeb propose``'s."""

    return tqdm(total=total, desc="reeb tune", unit="trial", disable=True if quiet else None, file=sys.stderr,
                dynamic_ncols=True)


def _changed(base: ReebConfig, cfg: ReebConfig) -> dict[str, Any]:
    """The fields of ``cfg`` that differ from the package default (what the config file holds)."""
    default = ReebConfig().to_dict()
    return {k: v for k, v in cfg.to_dict().items() if default[k] != v}


def plot_paths(stem: Path) -> list[Path]:
    """The pictures :func:`plot_study` may write beside ``<stem>.json``."""
    return [stem.with_name(stem.name + "_trials.png"), stem.with_name(stem.name + "_importances.png")]


def check_out(out: Path, overwrite: bool) -> None:
    """``-o`` before any work: a usage error (one line, exit 2) where it or a plot beside it
    is there already without ``overwrite``, or it is a folder."""

    claim_files([out, *plot_paths(out.with_suffix(""))], overwrite, example="tuned.json")


def _save(fig: Any, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    replace_file(path, buf.getvalue())


def plot_study(study: Any, stem: Path) -> list[Path]:
    """``<stem>_trials.png`` (recall per trial and the best so far) and, where Optuna can
    compute them, ``<stem>_importances.png``; nothing without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    done = [t for t in study.trials if t.value is not None]
    if not done:
        return []
    out = []
    fig, ax = plt.subplots(figsize=(7, 4))
    vals = [100 * t.value for t in done]
    ax.plot([t.number for t in done], vals, "o", ms=4, label="trial")
    ax.plot([t.number for t in done], [max(vals[: i + 1]) for i in range(len(vals))], "-", label="best so far")
    ax.set_xlabel("trial")
    ax.set_ylabel("recall (%)")
    ax.legend()
    fig.tight_layout()
    trials_png, importances_png = plot_paths(stem)
    _save(fig, trials_png)
    plt.close(fig)
    out.append(trials_png)
    try:
        import optuna

        imp = optuna.importance.get_param_importances(study)
    except Exception as e:  # too few trials, or an evaluator's optional dependency missing
        print(f"note: no parameter importances ({type(e).__name__}: {e})", file=sys.stderr)
        return out
    fig, ax = plt.subplots(figsize=(7, 4))
    names = list(imp)[::-1]
    ax.barh(names, [imp[n] for n in names])
    ax.set_xlabel("importance (optuna.importance, its default evaluator)")
    fig.tight_layout()
    _save(fig, importances_png)
    plt.close(fig)
    out.append(importances_png)
    return out


def _cv_lines(cv: T.CrossValidation, frames: T.Frames, objective: str) -> list[str]:
    comp = compare_recall(cv.base_hits, cv.tuned_hits)
    lines = [f"cross-validated estimate ({len(cv.folds)} contiguous blocks of frames, nested; {objective}):",
             f"  tuned    {cv.tuned}", f"  base     {cv.base}",
             f"  paired: tuned against base {comp}"]
    for f, (block, (t, b)) in enumerate(zip(cv.folds, cv.per_fold)):
        lines.append(f"  block {f}: frames {frames.ids[block[0]]}..{frames.ids[block[-1]]} ({len(block)}): "
                     f"tuned {100 * t:.1f} %, base {100 * b:.1f} %; {cv.best[f] or 'base settings'}")
    return lines


def run_tune(roots: Sequence[str], out: str, base: ReebConfig, space_file: str | None, trials: int, folds: int,
             seed: int, storage: str | None, resume: bool, timeout: float | None, balanced: bool, k: int,
             iou: float, limit: int | None = None, quiet: bool = False, plots: bool = True) -> dict[str, Any]:
    """The whole of ``reeb tune``; returns the record written to ``out``.

    Raises:
        ValueError: no labels, unknown search-space fields, fewer frames than folds, --resume
            without --storage, a stored study without --resume.
    """
    space = T.load_space(space_file)
    if resume and not storage:
        raise ValueError("--resume needs --storage (the SQLite file the interrupted run wrote)")
    frames = T.load_frames(roots, limit=limit)
    T.fold_blocks(len(frames), folds)  # refuse fewer frames than folds before any work
    opts = T.StudyOptions(trials=trials, seed=seed, storage=storage, resume=resume, k=k, iou=iou,
                          balanced=balanced,
                          deadline=None if timeout is None else time.monotonic() + timeout)
    opts.name = T.study_prefix(frames, base, space, folds, opts)
    bar = _progress(trials * (folds + 1), quiet)
    opts.on_trial = bar.update
    cache = T.FrameCache(frames)
    t0 = time.monotonic()
    try:
        cv = T.cross_validate(cache, base, space, folds, opts)
        tuned, study = T.tune(cache, base, space, opts)
    finally:
        bar.close()
    objective = f"{'class-balanced' if balanced else 'micro'} recall at {k} proposals, IoU {iou}"
    lines = [f"{len(frames)} frames, {sum(len(g) for g in frames.gts)} objects; {trials} trials per study, "
             f"seed {seed}; {time.monotonic() - t0:.0f} s"]
    lines += _cv_lines(cv, frames, objective)
    full = T.score_config(cache, tuned, k=k, iou=iou, balanced=balanced)[0]
    lines.append(f"tuned on all frames (optimistic, the frames it was tuned on): {full}")
    lines.append(f"  settings: { {n: getattr(tuned, n) for n in space} }")
    record: dict[str, Any] = {
        "config": _changed(base, tuned),
        "tune": {
            "objective": objective, "k": k, "iou": iou, "balanced": balanced, "data": list(map(str, roots)),
            "frames": len(frames), "objects": sum(len(g) for g in frames.gts), "trials": trials, "folds": folds,
            "seed": seed, "storage": storage, "study": opts.name,
            "space": {n: p.to_dict() for n, p in space.items()},
            "estimate": vars(cv.tuned), "base_estimate": vars(cv.base),
            "paired": vars(compare_recall(cv.base_hits, cv.tuned_hits)),
            "per_fold": [{"frames": [frames.ids[b[0]], frames.ids[b[-1]]], "best": best, "tuned": t, "base": bb}
                         for b, best, (t, bb) in zip(cv.folds, cv.best, cv.per_fold)],
            "all_frames": vars(full), "trials_completed": len([t for t in study.trials if t.value is not None]),
        },
    }

    replace_file(Path(out), (json.dumps(record, indent=2, default=str) + "\n").encode("utf-8"))
    pictures = plot_study(study, Path(out).with_suffix("")) if plots else []
    record["text"] = "\n".join(lines + [f"wrote {out}" + "".join(f", {p}" for p in pictures)])
    return record


def run_score(roots: Sequence[str], config: ReebConfig, base: ReebConfig, k: int, iou: float, balanced: bool,
              limit: int | None = None) -> str:
    """``reeb tune --score FILE``: FILE's settings against the base on the frames, no search."""
    frames = T.load_frames(roots, limit=limit)
    cache = T.FrameCache(frames)
    mine, hm = T.score_config(cache, config, k=k, iou=iou, balanced=balanced)
    ref, hb = T.score_config(cache, base, k=k, iou=iou, balanced=balanced)
    lines = [f"{'class-balanced' if balanced else 'micro'} recall at {k} proposals, IoU {iou}, "
             f"on {len(frames)} frames of {' '.join(map(str, roots))}:",
             f"  scored   {mine}", f"  base     {ref}", f"  paired: scored against base {compare_recall(hb, hm)}"]
    names = sorted(set(frames.folders))
    if len(names) > 1:
        for name in names:
            idx = [i for i, f in enumerate(frames.folders) if f == name]
            lab = [frames.labels[i] for i in idx]
            lines.append(f"  {name}: scored {100 * T.objective([hm[i] for i in idx], lab, balanced):.1f} %, "
                         f"base {100 * T.objective([hb[i] for i in idx], lab, balanced):.1f} %, "
                         f"paired {compare_recall([hb[i] for i in idx], [hm[i] for i in idx])}")
    return "\n".join(lines)
