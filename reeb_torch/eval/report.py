"""Table 3 rendered: the text tables, ``table3.csv``, ``table3.json`` and the plots.

:func:`write_report` writes, into one folder, what :func:`reeb_torch.eval.table3.compute`
computed:

- ``table3.txt`` (also printed): the rerun line, then for the selected frames (and for each
  folder and each frame range when there are several) 1. micro recall over all objects - the
  headline, as Table 3, with 100 and 300 proposals beside its 500 / 1000 / 2000 (there at IoU
  0.5 and 0.7 only: :data:`~reeb_torch.eval.methods.TEXT_GRID`); 2. micro recall over KITTI-moderate objects; 3. the mean of the
  per-class recalls; 4. the headline with its 95 % frame-bootstrap interval (on 60 frames
  about +-6 points, on 20 about +-10) and each method paired with the reference row (objects
  only it recalls, objects only the reference recalls, the exact sign test); 5. per-class
  recall at 2000 proposals, IoU 0.7; then AR at each k and the paper's own Table 3;
- ``table3.csv``: one row per method x frames x objects x average;
- ``table3.json``: every number, the settings and the machine (:func:`record`);
- ``recall_vs_proposals_iou0.7.png`` and ``recall_vs_iou_k2000.png``
  (:mod:`reeb_torch.eval.plots`, with matplotlib).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from ..metrics.recall import KITTI_DIFFICULTIES
from .common import environment, first_few
from .methods import CROSS_VALIDATED, HEADLINE, IOUS, KS, LEAVE_FOLDER_OUT, TEXT_GRID, WHOLE_DRIVES
from .plots import plot_curves
from .table3 import OBJECT_SETS, PAPER_TABLE3, Frames, Table3

__all__ = ["format_table", "format_per_class", "report_text", "write_csv", "record", "write_report"]


def _fmt(v: float | None, digits: int = 1) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _pct(v: float | None) -> float:
    return float("nan") if v is None else 100.0 * v


def format_table(title: str, rows: Sequence[tuple[str, Sequence[float | None], str]], note: str = "") -> str:
    """Plain-text table in Table 3's layout: ``rows`` are (name, recalls in % at the columns of
    :data:`~reeb_torch.eval.methods.TEXT_GRID` in order, time)."""
    name_w = max([30, *(len(r[0]) for r in rows)])
    groups = [" ".join(f"{f'IoU {t:g}':>7}" for t in ious) for _, ious in TEXT_GRID]
    head1 = f"{'':<{name_w}} | " + " | ".join(f"{f'{k} proposals':^{len(g)}}" for (k, _), g in zip(TEXT_GRID, groups))
    head2 = f"{'Method':<{name_w}} | " + " | ".join(groups) + " | ms/img"
    lines = [title, head1 + " | time", head2, "-" * len(head2)]
    for name, vals, t in rows:
        cells, at = [], 0
        for _, ious in TEXT_GRID:
            cells.append(" ".join(f"{_fmt(v):>7}" for v in vals[at : at + len(ious)]))
            at += len(ious)
        lines.append(f"{name:<{name_w}} | " + " | ".join(cells) + f" | {t}")
    if note:
        lines.append(note)
    return "\n".join(lines)


def _paper_row(values: Sequence[float]) -> list[float | None]:
    """The paper's nine recalls (500 / 1000 / 2000 x IoU 0.3 / 0.5 / 0.7) at the text
    columns; ``None`` where it gives none (100 and 300 proposals)."""
    given = {(k, t): v for (k, t), v in zip(((k, t) for k in (500, 1000, 2000) for t in IOUS), values)}
    return [given.get((k, t)) for k, ious in TEXT_GRID for t in ious]


def format_per_class(title: str, rows: list[tuple[str, dict[str, dict]]], classes: Sequence[str]) -> str:
    """Per-class recall at :data:`HEADLINE`: one row per method, for all and moderate
    objects a column "all" (micro) then one per class. ``rows`` are
    ``(name, {objects: recall dict})`` with recall dicts as :meth:`RecallResult.to_dict`."""
    k, t = str(HEADLINE[0]), f"{HEADLINE[1]:g}"
    first = rows[0][1] if rows else {}
    cols: list[tuple[str, str, str | None]] = []  # (header, objects, class or None = micro)
    for objects in OBJECT_SETS:
        if objects not in first:
            continue
        n = first[objects]["num_objects"]
        cols.append((f"all ({n})", objects, None))
        for c in classes:
            cols.append((f"{c} ({first[objects]['num_per_class'].get(c, 0)})", objects, c))
    width = max(11, *(len(h) for h, _, _ in cols)) if cols else 11
    name_w = max(30, *(len(r[0]) for r in rows)) if rows else 30
    groups = []
    for objects in OBJECT_SETS:
        n_cols = sum(1 for _, o, _ in cols if o == objects)
        if n_cols:
            label = "all objects" if objects == "all" else "KITTI-moderate objects"
            groups.append(f"{label:^{n_cols * (width + 1) - 1}}")
    head1 = f"{'':<{name_w}} | " + " | ".join(groups)
    head2 = f"{'Method':<{name_w}} | " + " | ".join(
        " ".join(f"{h:>{width}}" for h, o, _ in cols if o == objects) for objects in OBJECT_SETS
        if any(o == objects for _, o, _ in cols))
    lines = [title, head1, head2, "-" * len(head2)]
    for name, rec in rows:
        cells = []
        for objects in OBJECT_SETS:
            if objects not in rec:
                continue
            r = rec[objects]
            vals = [r["micro"][k][t]] + [r["per_class"][c][k][t] for c in classes]
            cells.append(" ".join(f"{_fmt(_pct(v)):>{width}}" for v in vals))
        lines.append(f"{name:<{name_w}} | " + " | ".join(cells))
    return "\n".join(lines)


def _class_counts(labels: list[torch.Tensor], n: int) -> list[int]:
    if not labels:
        return [0] * n
    return torch.bincount(torch.cat(labels).to(torch.int64), minlength=n).tolist()


def _frame_span(ids: Sequence[str]) -> str:
    return f"{ids[0]}-{ids[-1]}" if ids else "none"


def _in_sample_note(seen: dict[str, dict[str, str]], frames: Frames, results: dict[str, Any]) -> str:
    if not seen:
        return ""
    ids = next(iter(seen.values()))
    rows = ", ".join(results[k]["label"] for k in seen)
    return (f"In-sample: {len(ids)} of these {len(frames.images)} frames are pictures the learned ranking was "
            f"fitted on ({first_few(list(ids))}; table3.json: in_sample), so the rows ranked by it ({rows}) are not an "
            "estimate there; --exclude-fitted leaves them out.")


def report_text(table: Table3, rerun: str, env: dict[str, Any]) -> str:
    """The text of ``table3.txt``: the rerun line, the header (with a note where a learned
    ranking was fitted on some of the frames: :attr:`Table3.in_sample`), then the tables of
    each split, the AR lines and the paper's Table 3. ``env``:
    :func:`reeb_torch.eval.common.environment`."""
    opts, frames, results, done = table.options, table.frames, table.results, table.done
    blocks = []
    for split, idx in table.splits:
        blocks += _split_blocks(table, split, idx)
    at = " / ".join(f"@{k}" for k in KS)
    ar_lines = [f"Average recall (%, IoU 0.5:0.05:0.95, all objects)   micro {at}  |  class mean {at}"]
    width = _label_width(results, done)
    for k in done:
        a, c = results[k]["ar_micro"], results[k]["ar_class_mean"]
        ar_lines.append(f"{results[k]['label']:<{width}} " + " / ".join(f"{_fmt(_pct(a[str(kk)])):>5}" for kk in KS)
                        + "  |  " + " / ".join(f"{_fmt(_pct(c[str(kk)])):>5}" for kk in KS))
    blocks.append("\n".join(ar_lines))
    blocks.append(format_table(
        "The paper's Table 3 (7481 KITTI frames, C++ on an i7-8750H; its Edge Boxes uses SE edges)",
        [(n, _paper_row(v), f"{t:,}") for n, (v, t) in PAPER_TABLE3.items()]))
    counts = ", ".join(f"{c} {n}" for c, n in zip(frames.classes, _class_counts(frames.labels, len(frames.classes))))
    frames_note = f", --frames {' '.join(r.text for r in opts.frames)}" if opts.frames else ""
    if opts.exclude_fitted:
        frames_note += ", --exclude-fitted: frames a learned ranking was fitted on left out"
    header = (f"Table 3 on {len(frames.images)} frames of {opts.data_text} ({_frame_span(frames.ids)}{frames_note}; "
              f"{frames.n_obj} objects: {counts}).\n"
              f"Columns: recall at IoU 0.3 / 0.5 / 0.7 of the top 500 / 1000 / 2000 proposals, as Table 3, and at "
              f"IoU 0.5 / 0.7 of the top 100 / 300 (table3.json and table3.csv: IoU 0.3 too).\n"
              f"Time: wall ms per image of the proposal call only (decoding excluded), batch size 1"
              f"{f'; REEB also at batch {opts.batch} (@b{opts.batch})' if opts.batch > 1 else ''}; "
              f"{env['processor']}, {env['cpu_count']} cores, torch threads {env['torch_threads']}, "
              f"OpenCV threads {env['opencv_threads']}, CUDA {'yes' if env['cuda'] else 'no'}.")
    notes = [n for n in (_in_sample_note(table.in_sample, frames, results), _held_out_note(table)) if n]
    return "\n\n".join([f"Rerun: {rerun}", header, *notes, *blocks]) + "\n"


def _held_out_note(table: Table3) -> str:
    """What the rows ranked by held-out models (--whole-drives, --cross-validate,
    --leave-folder-out) are; the whole-drives row is the estimate to read first."""
    results, done = table.results, table.done
    lines = []
    for k in (WHOLE_DRIVES, CROSS_VALIDATED, LEAVE_FOLDER_OUT):
        if k not in done:
            continue
        t, label = results[k]["timing"], results[k]["label"]
        if k == WHOLE_DRIVES:
            lines.append(
                f"Whole drives held out - the estimate to read first: the row {label} ranks each of {t['folds']} "
                "blocks of these frames with a model fitted on the other blocks less every frame of the block's "
                "drives and every near-copy of a block frame (drives as the ids name them, as KITTI tracking's "
                "t0000_000012; KITTI object ids name none, so there near-copies alone stay out; reeb fit's options "
                f"and seed, the same models as reeb fit --folds {t['folds']} --whole-drives; {t['fit_s']:.0f} s in "
                "all). It estimates recall on drives no model saw; the cross-validated row keeps out only a "
                "block's drive neighbours within 2 frames.")
        elif k == CROSS_VALIDATED:
            lines.append(
                f"Cross-validated: the row {label} ranks each of {t['folds']} blocks of these frames with a model "
                "fitted on the other blocks (no drive neighbour within 2 frames or near-copy of a block on the "
                f"training side; reeb fit's options and seed, the same models as reeb fit --folds {t['folds']}; "
                f"{t['fit_s']:.0f} s in all).")
        else:
            lines.append(
                f"Other folders: the row {label} ranks each data folder's frames with a model fitted on the other "
                f"folders (reeb fit's options and seed; {t['fit_s']:.0f} s in all).")
    if lines:
        lines.append(f"These rows are estimates; every row is paired with {results[table.reference or done[0]]['label']}.")
    return "\n".join(lines)


def _split_blocks(table: Table3, split: str, idx: list[int]) -> list[str]:
    """The tables of one split of the frames: micro, moderate (and, for all frames, the
    class mean), the headline with its interval and pairings, the per-class table."""
    frames, results, done, batch = table.frames, table.results, table.done, table.options.batch

    def time_cell(k: str) -> str:
        t = results[k]["timing"]
        if t["ms_per_img"] is None:
            return f"(fit {t['fit_s']:.0f} s)"
        s = f"{t['ms_per_img']:.0f}"
        bk = f"ms_per_img_batch{batch}"
        return s + (f" ({t[bk]:.0f} @b{batch})" if bk in t else "")

    def grid_rows(objects: str, average: str) -> list[tuple[str, list[float], str]]:
        rows = []
        for k in done:
            grid = results[k]["splits"][split][objects]["recall"][average]
            vals = [_pct(grid[str(kk)][f"{t:g}"]) for kk, ious in TEXT_GRID for t in ious]
            rows.append((results[k]["label"], vals, time_cell(k)))
        return rows

    mod_rule = KITTI_DIFFICULTIES["moderate"]
    mod_text = (f"height >= {mod_rule.min_height:g} px, occlusion <= {mod_rule.max_occlusion}, "
                f"truncation <= {mod_rule.max_truncation:g}")
    blocks = []
    span = f"{len(idx)} frames {_frame_span([frames.ids[i] for i in idx])}"
    name = _split_name(split)
    where = span if split == "all" else f"{name} ({span})"
    if len(table.splits) > 1:
        blocks.append(f"=== {'all selected frames' if split == 'all' else name}: {span} ===")
    any_rec = results[done[0]]["splits"][split] if done else None
    n_all = any_rec["all"]["recall"]["num_objects"] if any_rec else 0
    n_mod = any_rec["moderate"]["recall"]["num_objects"] if any_rec else 0
    blocks.append(format_table(
        f"Recall (%) over all objects (micro, {n_all} objects, {where}) - headline, as Table 3",
        grid_rows("all", "micro")))
    blocks.append(format_table(
        f"Recall (%) over KITTI-moderate objects (micro, {n_mod} objects: {mod_text})",
        grid_rows("moderate", "micro")))
    if split == "all":
        blocks.append(format_table(
            f"Recall (%), mean of the per-class recalls ({', '.join(frames.classes)}; all objects)",
            grid_rows("all", "class_mean")))
    blocks.append(_interval_block(split, results, done, table.reference))
    blocks.append(format_per_class(
        f"Per-class recall (%) at {HEADLINE[0]} proposals, IoU {HEADLINE[1]:g} ({where})",
        [(results[k]["label"], {o: results[k]["splits"][split][o]["recall"] for o in OBJECT_SETS})
         for k in done], frames.classes))
    return blocks


def _label_width(results: dict[str, Any], done: Sequence[str]) -> int:
    """The width of the label column of the one-line-per-method blocks."""
    return max([30, *(len(results[k]["label"]) for k in done)])


def _split_name(split: str) -> str:
    """How the tables name a split: ``frames 0:39`` for a frame range, ``folder kitti`` for a
    data folder."""
    return f"frames {split}" if split.replace(":", "").isdigit() else f"folder {split}"


def _interval_block(split: str, results: dict[str, Any], done: list[str], reference: str | None) -> str:
    """The headline of each method with its 95 % interval, and its pairing with the reference."""
    ci_rows = []
    width = _label_width(results, done)
    for k in done:
        ci = results[k]["splits"][split]["headline_interval"]
        ci_rows.append(f"{results[k]['label']:<{width}} {100 * ci['recall']:5.1f}   {100 * ci['low']:5.1f} - "
                       f"{100 * ci['high']:5.1f}")
    for k in done:
        if reference is not None and k != reference:
            v = results[k]["splits"][split]["versus_reference"]
            ci_rows.append(f"{results[k]['label']:<{width}} vs {results[reference]['label']}: +{v['gained']} / "
                           f"-{v['lost']} objects, p = {v['p_value']:.2g}")
    return "\n".join([f"Recall (%) at {HEADLINE[0]} proposals, IoU {HEADLINE[1]:g}, all objects, with its "
                      "95 % interval (frames drawn with replacement, 4000 draws); each row paired with "
                      "the reference on the same objects (+ found by the row only / - by the reference "
                      "only, exact two-sided sign test)", *ci_rows])


def write_csv(table: Table3, path: str | os.PathLike) -> None:
    """``table3.csv``: one row per method × frames × objects × average."""
    results, batch, classes = table.results, table.options.batch, table.frames.classes
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "label", "frames", "objects", "average", "num_objects"]
                   + [f"R@{k}_IoU{t:g}" for k in KS for t in IOUS]
                   + [f"AR@{k}" for k in KS] + ["ms_per_img", f"ms_per_img_batch{batch}"])
        for k in table.done:
            r = results[k]
            for split, _ in table.splits:
                for objects in OBJECT_SETS:
                    rec = r["splits"][split][objects]
                    rows = [("micro", rec["recall"]["micro"], rec["ar"]["micro"], rec["recall"]["num_objects"]),
                            ("class_mean", rec["recall"]["class_mean"], rec["ar"]["class_mean"], "")]
                    rows += [(c, rec["recall"]["per_class"][c], rec["ar"]["per_class"][c],
                              rec["recall"]["num_per_class"][c]) for c in classes]
                    for average, grid, ar, n in rows:
                        w.writerow([k, r["label"], split, objects, average, n]
                                   + [_fmt(_pct(grid[str(kk)][f"{t:g}"]), 2) for kk in KS for t in IOUS]
                                   + [_fmt(_pct(ar[str(kk)]), 2) for kk in KS]
                                   + [_fmt(r["timing"]["ms_per_img"], 1),
                                      _fmt(r["timing"].get(f"ms_per_img_batch{batch}"), 1)])


def record(table: Table3, rerun: str, env: dict[str, Any], plots: Sequence[str] = ()) -> dict[str, Any]:
    """The JSON record of ``table3.json``: the settings, the frames, the machine (``env``),
    every method's numbers (:attr:`Table3.results`), the paper's table and the plots' files."""
    opts, frames = table.options, table.frames
    mod_rule = KITTI_DIFFICULTIES["moderate"]
    return {
        "rerun": rerun,
        "data": [str(d) for d in opts.data],
        "num_images": len(frames.images),
        "image_ids": frames.ids,
        "frames": [r.text for r in opts.frames],
        "splits": {name: [frames.ids[i] for i in idx] for name, idx in table.splits},
        "num_objects": frames.n_obj,
        "classes": list(frames.classes),
        "ks": list(KS),
        "ious": list(IOUS),
        "moderate": {"min_height": mod_rule.min_height, "max_occlusion": mod_rule.max_occlusion,
                     "max_truncation": mod_rule.max_truncation},
        "top_k": opts.top_k,
        "batch": opts.batch,
        "environment": env,
        "methods": table.results,
        "paper_table3": {n: {"recall": v, "ms_per_img": t} for n, (v, t) in PAPER_TABLE3.items()},
        "plots": list(plots),
        "in_sample": table.in_sample,
        "excluded_fitted": table.excluded,
    }


def write_report(table: Table3, out: str | os.PathLike, rerun: str = "") -> dict[str, Any]:
    """Print the tables and write ``table3.txt``, ``table3.csv``, ``table3.json`` and the
    plots into ``out`` (made if needed); ``rerun`` is the command line that makes them again.
    Returns the JSON record (:func:`record`)."""

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    env = environment()
    text = report_text(table, rerun, env)
    print("\n" + text, flush=True)
    (out / "table3.txt").write_text(text)
    write_csv(table, out / "table3.csv")
    in_sample = [table.results[k]["label"] for k in table.in_sample]
    plots = plot_curves(table.curves, out, in_sample) if table.curves else []
    rec = record(table, rerun, env, plots)
    (out / "table3.json").write_text(json.dumps(rec, indent=1))
    print(f"wrote {out}/table3.txt, table3.csv, table3.json" + (f", {', '.join(plots)}" if plots else ""), flush=True)
    return rec
