"""Ablations that settle the paper's ambiguities (the readings in docs/results.md) by measured recall.

The first rows are the package default (``ReebConfig()``: REEB's windows ranked by the
shipped learned model), a few changes of its learned ranking, and the ``training-free``
setting (no learned part); every other row changes one switch of the training-free
ranking, or starts from the ``paper`` preset. Each reports recall of the top 2000 proposals at IoU 0.5 and 0.7
(micro, all objects of the four classes), recall at 0.7 of KITTI-moderate objects, AR, and
ms/img, on the same KITTI frames; the JSON rows add the per-class recall at 0.7.
``--data`` takes several folders (default: the two dev folders beside the repository,
``../shared/data/kitti`` and ``../shared/data/kitti_tracking``): every row then also gives
R@0.7 of each folder and its pairing with the default there. ``--frames 0:39 40:59``
(numeric ids, both ends included) adds the same for each range.

Each row is also paired with the default (or the ``--reference`` row: on the dev frames,
whose objects the default's ranking model was fitted on, ``--reference training-free``) on
the same objects (R@2000, IoU 0.7): ``+g/-l``
counts the objects it finds that the default misses and the other way round, and ``p`` is
the two-sided exact sign test of that split (:func:`reeb_torch.metrics.recall.compare_recall`).
On the 106 dev frames a difference of a few objects is p ≈ 0.3-1: not a finding. The default's
row gives its recall's 95 % frame-bootstrap interval instead
(:func:`reeb_torch.metrics.recall.recall_interval`).

``--variant "FIELD=VALUE;FIELD=VALUE"`` (repeatable; fields and values as ``reeb propose
--set``) adds a row for any setting of the default: with it, only the default and these
rows run (plus the named rows ``--only`` picks). To check a choice on frames of your own,
e.g. ``--data HELD_OUT --variant thin_edges=off --variant blur_sigma=1.5``.

Rerun: ``python benchmarks/ablations.py [--data DIR ...] [--limit N] [--frames A:B ...]
[--only NAME ...] [--variant SETTINGS ...]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, environment, rerun_line, setting_pairs, settings_config  # noqa: E402

from reeb_torch import ProposalGenerator, ReebConfig  # noqa: E402
from _common import add_data_option, add_frames_option  # noqa: E402
from reeb_torch.datasets.folders import folder_splits, load_folders  # noqa: E402
from reeb_torch.eval.common import first_few  # noqa: E402
from reeb_torch.eval.table3 import moderate_masks  # noqa: E402
from reeb_torch.metrics.recall import (  # noqa: E402
    average_recall,
    compare_recall,
    object_hits,
    recall_interval,
    recall_table,
    select_objects,
)

D = ReebConfig()
TF = D.training_free()
"""The hand-set rows change one switch of the training-free ranking (no learned model)."""
P = ReebConfig.paper()

# name -> (config, the reading of docs/results.md it settles)
VARIANTS: dict[str, tuple[ReebConfig, str]] = {
    "default": (D, "package default (learned ranking)"),
    "training-free": (TF, "no learned ranking"),
    "ranker_keep=8000": (D.replace(ranker_keep=8000), "ranker"),
    "ranker_keep=20000": (D.replace(ranker_keep=20000), "ranker"),
    "ranker, candidates_per_region=20000": (D.replace(candidates_per_region=20000), "ranker"),
    "ranker, nms_iou=0.7": (D.replace(nms_iou=0.7), "ranker"),
    "class-quota": (D.replace(class_quota={"Pedestrian": 0.3, "Cyclist": 0.1, "Truck": 0.05}), "ranker"),
    "paper": (P, "printed text"),
    "window_geometry=grid": (TF.replace(window_geometry="grid"), "#13"),
    "min_window=12": (TF.replace(min_window=12), "#13"),
    "min_window=20": (TF.replace(min_window=20), "#13"),
    "location=classes, σ .5": (TF.replace(ground_log_sigma=0.5), "#11"),
    "class_weights=1,1,1,1": (TF.replace(class_weights=(1.0, 1.0, 1.0, 1.0)), "#11"),
    "shadow_score=none (no shadow term)": (TF.replace(shadow_score="none"), "shadow"),
    "shadow_strip=0.12": (TF.replace(shadow_strip=0.12), "shadow"),
    "shadow_strip=0.3": (TF.replace(shadow_strip=0.3), "shadow"),
    "shadow_power=0.25": (TF.replace(shadow_power=0.25), "shadow"),
    "shadow_power=1": (TF.replace(shadow_power=1.0), "shadow"),
    "shadow_margin=0.05": (TF.replace(shadow_margin=0.05), "shadow"),
    "vegetation_score=none": (TF.replace(vegetation_score="none"), "vegetation"),
    "vegetation_box=1 (whole window)": (TF.replace(vegetation_box=1.0), "vegetation"),
    "vegetation_box=1, power 3": (TF.replace(vegetation_box=1.0, vegetation_power=3), "vegetation"),
    "vegetation_box=0.5": (TF.replace(vegetation_box=0.5), "vegetation"),
    "vegetation_power=3": (TF.replace(vegetation_power=3), "vegetation"),
    "vegetation_power=4": (TF.replace(vegetation_power=4), "vegetation"),
    "vegetation_power=6": (TF.replace(vegetation_power=6), "vegetation"),
    "vegetation=none, nms_iou=0.7": (TF.replace(vegetation_score="none", nms_iou=0.7), "vegetation, #14"),
    "kappa=1.5 (Edge Boxes)": (TF.replace(kappa=1.5), "#1"),
    "nms_iou=0.7 (eq. 13 as printed)": (TF.replace(nms_iou=0.7), "#14"),
    "nms_iou=0.72": (TF.replace(nms_iou=0.72), "#14"),
    "candidates_per_region=4000": (TF.replace(candidates_per_region=4000), "eq. 9"),
    "training-free, no regions": (TF.replace(use_regions=False), "Ours* vs Ours**"),
    "norm=area (γ=0.75)": (TF.replace(score_norm="area"), "#1"),
    "kappa=1.25": (TF.replace(kappa=1.25), "#1"),
    "kappa=1.75": (TF.replace(kappa=1.75), "#1"),
    "group_cell=None (unbounded)": (TF.replace(group_cell=None), "#2"),
    "group_cell=4": (TF.replace(group_cell=4), "#2"),
    "group_cell=16": (TF.replace(group_cell=16), "#2"),
    "edge_threshold=0.1": (TF.replace(edge_threshold=0.1), "#4"),
    "edge_threshold=0.02": (TF.replace(edge_threshold=0.02), "#4"),
    "blur_sigma=0.7": (TF.replace(blur_sigma=0.7), "#4"),
    "blur_sigma=1.5": (TF.replace(blur_sigma=1.5), "#4"),
    "thin_edges=off": (TF.replace(thin_edges=False), "#4"),
    "entropy_bins=16": (TF.replace(entropy_bins=16), "#9"),
    "road_score=reward": (TF.replace(road_score="reward"), "#10"),
    "location=paper": (TF.replace(location_score="paper"), "#11"),
    "location=none": (TF.replace(location_score="none"), "#11"),
    "min_edge_score=0.01": (TF.replace(min_edge_score=0.01), "#12"),
    "region_assign=contained": (TF.replace(region_assign="contained"), "#13"),
    "grid, ground_band=off": (TF.replace(window_geometry="grid", ground_band=None), "#13"),
    "window_step=0.1": (TF.replace(window_step=0.1), "#13"),
    "window_step=0.2": (TF.replace(window_step=0.2), "#13"),
    "size_ratio=1.15": (TF.replace(size_ratio=1.15), "#13"),
    "scale=1.0": (TF.replace(scale=1.0, group_cell=16), "#13"),
    "nms_iou=0.8": (TF.replace(nms_iou=0.8), "#14"),
    "candidates_per_region=6000": (TF.replace(candidates_per_region=6000), "eq. 9"),
    "candidates_per_region=8000": (TF.replace(candidates_per_region=8000), "eq. 9"),
}


def load(roots: list[Path], limit: int | None, frames=()):
    items, classes = load_folders(roots, limit=limit, frames=frames)
    return [it["image"] for it in items], [it["boxes"] for it in items], [it["labels"] for it in items], classes, items


def run(cfg: ReebConfig, images, batch: int) -> tuple[list[torch.Tensor], float]:
    gen = ProposalGenerator(cfg)
    gen(images[:1])  # warm-up (window grids are cached per size)
    boxes: list[torch.Tensor] = []
    t0 = time.perf_counter()
    for i in range(0, len(images), batch):
        boxes += [o["boxes"] for o in gen(images[i: i + batch])]
    return boxes, (time.perf_counter() - t0) * 1000 / len(images)


def parse_args(argv: list[str] | None) -> tuple[argparse.Namespace, dict]:
    """The options, and the ``--variant`` rows as ``{name: (config, "set")}`` (a usage error,
    before any work, for an unknown field or a bad value)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_option(ap, default_dev_dirs())
    ap.add_argument("--limit", type=int, default=None, help="only the first N frames of each folder")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (substring match)")
    ap.add_argument("--variant", action="append", default=[], metavar="SETTINGS",
                    help="a row of its own: FIELD=VALUE pairs on the default, separated by ';' "
                         "(as reeb propose --set), e.g. 'blur_sigma=1.5;kappa=1.5'; repeatable")
    add_frames_option(ap)
    ap.add_argument("--out", type=Path, default=Path("runs/ablations"))
    ap.add_argument("--reference", default="default", choices=sorted(VARIANTS),
                    help="the row every other row is paired with (default: the package default; on the "
                         "frames its ranking model was fitted on, pair with training-free)")
    args = ap.parse_args(argv)
    extra = {}
    for text in args.variant:
        try:
            extra[", ".join(setting_pairs(text))] = (settings_config(text), "set")
        except ValueError as e:  # an unknown field, a bad value: before any work
            ap.error(f"--variant {text!r}: {e}")
    try:
        args.frames_data = load(args.data, args.limit, args.frames)
    except ValueError as e:
        ap.error(str(e))
    return args, extra


def groups_of(args: argparse.Namespace, items: list[dict]) -> list[tuple[str, list[int]]]:
    """The frame groups each row also reports: every data folder (when there are several),
    then every ``--frames`` range (when there are several)."""
    groups = folder_splits(items)
    if len(args.frames) > 1:
        groups += [(r.text, [i for i, it in enumerate(items) if int(it["image_id"]) in r]) for r in args.frames]
    return groups


def main(argv: list[str] | None = None) -> list[dict]:
    args, extra = parse_args(argv)
    images, gts, labels, classes, items = args.frames_data
    lines: list[str] = []

    def say(text: str) -> None:  # printed as it comes, and kept for ablations.txt
        print(text, flush=True)
        lines.append(text)

    say("# rerun: " + rerun_line("benchmarks/ablations.py", argv if argv is not None else sys.argv[1:]))
    gts_mod, labels_mod = select_objects(gts, labels, moderate_masks(items))
    groups = groups_of(args, items)
    say(f"# {len(images)} images from {' + '.join(map(str, args.data))}, {sum(len(g) for g in gts)} objects "
        f"({sum(len(g) for g in gts_mod)} moderate), torch threads {torch.get_num_threads()}")

    def selected(name: str) -> bool:
        if name in extra:
            return True
        if args.only is None:  # with --variant: the default and those rows, not every named row
            return not extra or name == args.reference
        return not args.only or any(s in name for s in args.only)

    say_in_sample(say, {table_cfg.ranker for name, (table_cfg, _) in {**VARIANTS, **extra}.items()
                        if selected(name) or name == args.reference}, images, items)
    say(f"{'variant':34s} {'NOTES':6s} {'R@.5':>6s} {'R@.7':>6s} {'mod.7':>6s} {'AR':>6s} {'ms/img':>7s}"
        + "".join(f" {'.7 ' + g:>{max(9, len(g) + 3)}s}" for g, _ in groups) + f"  vs {args.reference} (+g/-l, p; per group)")
    base_hits = None
    if not selected(args.reference):  # every row is paired with the reference: run it unlisted
        base_hits = object_hits(run(VARIANTS[args.reference][0], images, args.batch)[0], gts)
    rows = []
    table = {**VARIANTS, **extra}
    order = sorted(table, key=lambda n: n != args.reference)  # the reference first: the others pair with it
    for name in order:
        cfg, note = table[name]
        if not selected(name):
            continue
        boxes, ms = run(cfg, images, args.batch)
        hits = object_hits(boxes, gts)
        if name == args.reference:
            base_hits = hits
        row, text = measure(name, note, boxes, ms, hits, base_hits, gts, labels, classes, gts_mod, labels_mod, groups)
        say(text)
        rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablations.json").write_text(json.dumps({"rows": rows, "env": environment()}, indent=2))
    (args.out / "ablations.txt").write_text("\n".join(lines) + "\n")
    return rows


def say_in_sample(say, rankers: set[str], images, items) -> None:
    """A line per learned ranking among the rows: how many of the frames it was fitted on
    (the same pictures, :func:`reeb_torch.ranker.fitted_frames`): its rows are in-sample there."""
    from reeb_torch.ranker import fitted_frames, load_ranker, seen_hashes

    for spec in sorted(r for r in rankers if r != "none"):
        model = load_ranker(spec)
        if not seen_hashes(model.meta.get("provenance", {})):
            say(f"# ranking {spec!r}: its file records no frame hashes (written before they were kept): "
                "which of these frames it saw is unknown")
            continue
        seen = [str(it["image_id"]) for it, n in zip(items, fitted_frames(model, images)) if n]
        say(f"# ranking {spec!r}: fitted on {len(seen)} of these {len(images)} frames"
            + (f" ({first_few(seen, 6)}): its rows are in-sample there" if seen
               else " (the same pictures, by frame hash)"))


def measure(name, note, boxes, ms, hits, base_hits, gts, labels, classes, gts_mod, labels_mod, groups):
    """One row of the table: its JSON record and its line of text. The default's row gives
    its 95 % frame-bootstrap interval, every other row its pairing with the default (over
    all frames, then per group)."""
    pairs = {}
    if hits is base_hits:
        ci = recall_interval(hits)
        versus, pair = f"95 % interval {100 * ci.low:.1f}-{100 * ci.high:.1f}", None
    else:
        cmp = compare_recall(base_hits, hits)
        versus = f"+{cmp.gained}/-{cmp.lost}, p {cmp.p_value:.2f}"
        pair = dict(gained=cmp.gained, lost=cmp.lost, p_value=cmp.p_value)
        for g, idx in groups:
            c = compare_recall([base_hits[i] for i in idx], [hits[i] for i in idx])
            pairs[g] = dict(gained=c.gained, lost=c.lost, p_value=c.p_value)
            versus += f"; {g} +{c.gained}/-{c.lost}"
    res = recall_table(boxes, gts, labels, classes, ks=(2000,), ious=(0.5, 0.7))
    ar = float(average_recall(boxes, gts, ks=(2000,))[0])
    r5, r7 = res.at(2000, 0.5), res.at(2000, 0.7)
    mod7 = recall_table(boxes, gts_mod, labels_mod, classes, ks=(2000,), ious=(0.7,)).at(2000, 0.7)
    per_group = {g: recall_table([boxes[i] for i in idx], [gts[i] for i in idx], ks=(2000,), ious=(0.7,)).at(2000, 0.7)
                 for g, idx in groups}
    text = (f"{name:34s} {note:6s} {100 * r5:6.1f} {100 * r7:6.1f} {100 * mod7:6.1f} {100 * ar:6.1f} {ms:7.1f}"
            + "".join(f" {100 * v:{max(9, len(g) + 3)}.1f}" for g, v in per_group.items()) + f"  {versus}")
    per_class = {c: (None if v != v else v) for c, v in res.per_class_at(2000, 0.7).items()}  # nan: no object
    row = dict(variant=name, notes=note, recall_05=r5, recall_07=r7, ar=ar, ms_per_img=ms,
               recall_07_moderate=mod7, recall_07_per_class=per_class,
               recall_07_per_range=per_group, versus_default=pair, versus_default_per_range=pairs)
    return row, text


if __name__ == "__main__":
    main()
