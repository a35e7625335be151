"""Where REEB loses objects: recall after each stage of the pipeline, per class.

For each ground-truth object, the best IoU with (1) every sliding window of the grid
(coverage), (2) the windows with a valid score (S above ``min_edge_score``), (3) the
candidates the regions pass on (each region's top-k, eq. 9 budgets), (3b) those the learned
ranking's prefilter keeps (``ranker_keep``; all of them without a ranker), (4) the final
``top_k`` after NMS. Recall at IoU 0.5 and 0.7 over all objects (micro) and over
KITTI-moderate objects (height >= 25 px, occlusion <= 1, truncation <= 0.3), and recall at
IoU 0.7 of each class, on the frames of a KITTI-format folder. ``--frames 0:39 40:59``
(numeric ids, both ends included) also reports each range on its own. ``--folds N``: the
learned ranking's stages on frames it never saw — each frame is run with a model fitted
without its block of frames, as ``reeb fit --folds N`` estimates (``--seed``: the fit's);
``--whole-drives`` keeps every frame of a held-out block's drives off its training side, as
``reeb fit --whole-drives``; without ``--folds`` the settings' own model runs on every frame
(the shipped one saw the dev frames).

Rerun: ``python benchmarks/diagnose_recall.py [--data DIR ...] [--limit N] [--preset NAME]
[--set FIELD=VALUE ...] [--frames A:B ...] [--folds N [--seed S] [--whole-drives]] [--lost [--show IMAGE]]
[--json PATH]`` (``--set`` as in ``reeb propose``, e.g. ``--set min_window=12``; ``--lost`` lists each missed object with
the stage that lost it, ``--show`` draws them all in one picture)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Callable

import torch
from torchvision.ops import box_iou

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, rerun_line, run_captured  # noqa: E402

from reeb_torch import ProposalGenerator  # noqa: E402
from reeb_torch.config_text import config_from  # noqa: E402
from _common import add_data_option, add_frames_option  # noqa: E402
from reeb_torch.datasets.folders import folder_splits, load_folders  # noqa: E402
from reeb_torch.metrics.recall import kitti_difficulty_mask  # noqa: E402
from reeb_torch.stages.nms import nms_top_k  # noqa: E402
from reeb_torch.runs.viz import crop_sheet, save_png  # noqa: E402

STAGES = ("all windows", "valid score", "region candidates", "ranked candidates", "final top-k")


def stage_ious(gen: ProposalGenerator, image: torch.Tensor, gt: torch.Tensor,
               lost_detail: bool = False) -> tuple[dict[str, torch.Tensor], list[dict]]:
    """Best IoU of each object in ``gt`` at each stage, for one uint8 image; with
    ``lost_detail``, also :func:`lost_details` of the objects the final top-k misses."""
    out, captured = run_captured(gen, image)
    h, w = image.shape[-2:]
    s = gen.config.scale
    hk, wk = max(1, round(h * s)), max(1, round(w * s))
    boxes = captured["grid"].boxes / torch.tensor([wk / w, hk / h, wk / w, hk / h])
    iou = box_iou(gt, boxes)
    valid = torch.isfinite(captured["scores"][0])[None]
    chosen = captured["chosen"][0][None]
    ranked = captured.get("kept", captured["chosen"])[0][None]  # the learned ranking's prefilter
    final = box_iou(gt, out["boxes"]) if len(out["boxes"]) else torch.zeros(len(gt), 1)
    zero = torch.zeros(())
    best = {
        "all windows": iou.max(1).values,
        "valid score": torch.where(valid, iou, zero).max(1).values,
        "region candidates": torch.where(chosen, iou, zero).max(1).values,
        "ranked candidates": torch.where(ranked, iou, zero).max(1).values,
        "final top-k": final.max(1).values,
    }
    details = lost_details(gen, best, iou, boxes, captured) if lost_detail else []
    for d in details:  # the final proposal of best IoU with the object
        g = d["index"]
        d["nearest"] = ([round(float(v), 1) for v in out["boxes"][int(final[g].argmax())]]
                        if len(out["boxes"]) else None)
    return best, details


def lost_details(gen: ProposalGenerator, best: dict[str, torch.Tensor], iou: torch.Tensor,
                 boxes: torch.Tensor, captured: dict) -> list[dict]:
    """Why each object with no final proposal at IoU >= 0.7 was lost, one dict per such object
    (``index`` into the frame's objects): ``lost_at``, the first stage without a window at
    IoU >= 0.7 (``"nms"`` / ``"top-k"`` split the last stage: a good candidate suppressed by
    a better-scored box, or surviving NMS but ranked past ``top_k``); ``best_iou`` per stage;
    for objects with a valid good window, ``region_rank`` (windows of its region scoring
    higher than its best-scored good window) against ``region_budget``; after the region cut,
    ``nms_rank`` (0-based, among the candidates that survive NMS) or ``suppressed_by_iou``
    (the suppressing box's IoU with the object). The NMS is recomputed with the pipeline's
    own :func:`reeb_torch.stages.nms.nms_top_k` on the candidates, without the top-k cut."""
    cfg = gen.config
    scores, grid, chosen = captured["scores"][0], captured["grid"], captured["chosen"][0]
    budget = gen.selection.cut.region_budget(captured["share"][0])
    lost = torch.nonzero(best["final top-k"] < 0.7).squeeze(1).tolist()
    # what the NMS ranks: the learned ranking's candidates and logits, else the cut's and V
    order, cand = (captured["ranked"][0], torch.nonzero(captured["kept"][0]).squeeze(1)) if "kept" in captured \
        else (scores, torch.nonzero(chosen).squeeze(1))
    kept = cand[nms_top_k(boxes[cand], order[cand], cfg.nms_iou, len(cand))] if lost else None
    out = []
    for g in lost:
        d: dict = {"index": g, "best_iou": {k: round(float(v[g]), 3) for k, v in best.items()}}
        d["lost_at"] = next((k for k in STAGES if float(best[k][g]) < 0.7), "final top-k")
        good = torch.nonzero((iou[g] >= 0.7) & torch.isfinite(scores)).squeeze(1)
        if len(good):
            top = good[scores[good].argmax()]
            r = int(grid.region_of[top])
            d["region_rank"] = int((scores[grid.region_windows[r]] > scores[top]).sum())
            d["region_budget"] = int(budget[r])
        if d["lost_at"] == "final top-k" and kept is not None:
            hit = torch.nonzero(iou[g, kept] >= 0.7).squeeze(1)
            if len(hit):
                d["lost_at"], d["nms_rank"] = "top-k", int(hit[0])
            else:
                good_c = cand[iou[g, cand] >= 0.7]
                top_c = good_c[order[good_c].argmax()]
                over = torch.nonzero(box_iou(boxes[top_c][None], boxes[kept])[0] > cfg.nms_iou).squeeze(1)
                d["lost_at"] = "nms"
                if len(over):  # the first (best-scored) kept box over the threshold suppressed it
                    d["suppressed_by_iou"] = round(float(iou[g, kept[over[0]]]), 3)
        out.append(d)
    return out


def _pct(hit: torch.Tensor) -> float:
    return 100.0 * float(hit.float().mean()) if hit.numel() else float("nan")


def stage_table(best: dict[str, torch.Tensor], labels: torch.Tensor, moderate: torch.Tensor,
                classes: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """Per stage: recall (%) at IoU 0.5 / 0.7 over all objects, at 0.7 over moderate ones
    and at 0.7 per class (``nan`` where there is no object)."""
    out: dict[str, dict[str, float]] = {}
    for stage, b in best.items():
        row = {"R@0.5": _pct(b >= 0.5), "R@0.7": _pct(b >= 0.7), "moderate R@0.7": _pct(b[moderate] >= 0.7)}
        for ci, c in enumerate(classes):
            row[f"{c} R@0.7"] = _pct(b[labels == ci] >= 0.7)
        out[stage] = row
    return out


def format_stage_table(title: str, table: dict[str, dict[str, float]], labels: torch.Tensor,
                       moderate: torch.Tensor, classes: tuple[str, ...]) -> str:
    heads = ["R@0.5", "R@0.7", f"moderate ({int(moderate.sum())})"]
    heads += [f"{c} ({int((labels == ci).sum())})" for ci, c in enumerate(classes)]
    keys = ["R@0.5", "R@0.7", "moderate R@0.7"] + [f"{c} R@0.7" for c in classes]
    w = max(7, *(len(h) for h in heads))
    lines = [title, f"{'stage':20s} " + " ".join(f"{h:>{w}}" for h in heads)]
    for stage, row in table.items():
        cells = ["-" if v != v else f"{v:.1f}" for v in (row[k] for k in keys)]
        lines.append(f"{stage:20s} " + " ".join(f"{c:>{w}}" for c in cells))
    return "\n".join(lines)


LOST_AT = ("all windows", "valid score", "region candidates", "ranked candidates", "nms", "top-k", "final top-k")


SHORT = {"all windows": "no window", "valid score": "invalid", "region candidates": "region",
         "ranked candidates": "prefilter",
         "nms": "NMS", "top-k": "top-k", "final top-k": "final"}


def _caption(d: dict, cls: str, frame: str) -> str:
    """One line under an object's crop: frame, class, stage that lost it, its detail."""
    text = f"{frame} {cls[:3]} {SHORT[d['lost_at']]}"
    if d["lost_at"] == "region candidates":
        text += f" {d['region_rank']}/{d['region_budget']}"
    elif "nms_rank" in d:
        text += f" #{d['nms_rank']}"
    elif "suppressed_by_iou" in d:
        text += f" by {d['suppressed_by_iou']:.2f}"
    return text + f" iou {d['best_iou']['final top-k']:.2f}"


def format_lost(lost: list[dict]) -> str:
    """The objects the final top-k misses, one line each, after a count per stage."""
    counts = {k: sum(d["lost_at"] == k for d in lost) for k in LOST_AT}
    lines = [f"# {len(lost)} objects without a final proposal at IoU 0.7; lost at: "
             + ", ".join(f"{k} {n}" for k, n in counts.items() if n),
             f"{'frame':12s} {'class':10s} {'w x h':>9s} occ trunc {'lost at':17s} {'grid':>5s} {'final':>5s}  detail"]
    for d in lost:
        x1, y1, x2, y2 = d["box"]
        detail = []
        if "region_rank" in d:
            detail.append(f"region rank {d['region_rank']} / budget {d['region_budget']}")
        if "nms_rank" in d:
            detail.append(f"survives NMS at rank {d['nms_rank']}")
        if "suppressed_by_iou" in d:
            detail.append(f"suppressed by a box at IoU {d['suppressed_by_iou']:.2f}")
        lines.append(f"{d['frame']:12s} {d['class']:10s} {f'{x2 - x1:.0f}x{y2 - y1:.0f}':>9s} {d['occluded']:3d} "
                     f"{d['truncated']:5.2f} {d['lost_at']:17s} {d['best_iou']['all windows']:5.2f} "
                     f"{d['best_iou']['final top-k']:5.2f}  {'; '.join(detail)}")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data_option(ap, default_dev_dirs())
    ap.add_argument("--limit", type=int, default=None, help="only the first N frames of each folder")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a config field of the preset (repeatable)")
    add_frames_option(ap)
    ap.add_argument("--lost", action="store_true",
                    help="also list every object the final top-k misses: the stage that lost it, its best "
                         "window's rank in its region against the region's budget, its NMS fate")
    ap.add_argument("--show", type=Path, default=None, metavar="IMAGE",
                    help="with --lost: draw every missed object (its box green, the nearest proposal "
                         "orange, the stage that lost it below) in one picture (.png, or .jpg)")
    ap.add_argument("--folds", type=int, default=None, metavar="N",
                    help="run each frame with a ranking model fitted without its block of N blocks of frames "
                         "(reeb fit's cross-validation), not with the settings' own model")
    ap.add_argument("--seed", type=int, default=0, help="with --folds: the fit's seed (reeb fit --seed)")
    ap.add_argument("--whole-drives", action="store_true",
                    help="with --folds: every frame of a held-out block's drives off its training side "
                         "(reeb fit --whole-drives), not only those within 2 frames")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers to this JSON file")
    return ap


def held_out_generators(data: list[Path], limit: int | None, config, folds: int, seed: int,
                        whole_drives: bool = False) -> dict[tuple[str, str], Callable[[], ProposalGenerator]]:
    """Per frame ``(folder, image id)``, a function that makes the generator of ``config``
    with a ranking model fitted without the frame's block (:func:`reeb_torch.ranker.cv.cross_validate`'s
    folds, training frames and fit; the weights saved in a temporary folder that lives as
    long as the functions), the one generator per block made once, when its first frame asks;
    ``whole_drives``: every frame of a held-out block's drives stays off its training side."""
    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import fit as RF
    from reeb_torch.tuning import FrameCache, fold_blocks
    from reeb_torch.ranker import save_ranker

    frames = F.load_fit_frames(data, limit)
    cache = FrameCache(frames)
    opts = RF.FitOptions(seed=seed)
    samples = F.frame_samples(cache, config, opts)
    blocks = fold_blocks(len(frames), folds)
    similar = F.similar_frames(frames.images)
    names = cache.candidates(config.unranked(), 0).feature_names
    made: dict[int, ProposalGenerator] = {}
    tmp = tempfile.TemporaryDirectory(prefix="reeb-diagnose-")

    def maker(f: int) -> Callable[[], ProposalGenerator]:
        def make() -> ProposalGenerator:
            if f not in made:
                made.clear()  # one block's generator at a time: the frames come block by block
                train = F.training_frames(blocks, f, frames.ids, frames.folders, similar,
                                          len(frames) if whole_drives else 2)
                model = RF.fit_ranker([samples[i] for i in train], names, opts, frames.classes)
                path = save_ranker(model, Path(tmp.name) / f"fold{f}.safetensors")
                made[f] = ProposalGenerator(config.replace(ranker=str(path)))
            return made[f]
        return make

    return {(frames.folders[i], frames.ids[i]): maker(f) for f, block in enumerate(blocks) for i in block}


def _generators(ap: argparse.ArgumentParser, args: argparse.Namespace, config) -> Callable[[dict], ProposalGenerator]:
    """The generator that runs each frame (an item of ``load_folders``): the settings' own, or
    with ``--folds`` the one whose model was fitted without the frame's block."""
    if args.folds is None:
        gen = ProposalGenerator(config)
        return lambda item: gen
    if config.ranker == "none":
        ap.error("--folds fits the learned ranking: these settings have none (ranker='none')")
    try:
        held_out = held_out_generators(args.data, args.limit, config, args.folds, args.seed, args.whole_drives)
    except ValueError as e:  # fewer frames than folds, no labelled object
        ap.error(str(e))
    return lambda item: held_out[(item["folder"], str(item["image_id"]))]()


def _write_sheet(path: Path, crops: list, lost: list[dict]) -> None:
    """``--show``: the missed objects' crops, grouped by the stage that lost them."""
    order = sorted(range(len(crops)), key=lambda i: LOST_AT.index(lost[i]["lost_at"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet = crop_sheet([crops[i] for i in order], columns=8)
    if path.suffix.lower() in (".jpg", ".jpeg"):  # a fifth of the PNG's bytes for photos
        import cv2

        ok, data = cv2.imencode(".jpg", sheet[:, :, ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 85])
        path.write_bytes(data.tobytes())
    else:
        save_png(path, sheet)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> dict:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.show is not None and not args.lost:
        ap.error("--show draws the objects --lost lists: give --lost too")
    if args.whole_drives and args.folds is None:
        ap.error("--whole-drives holds out the drives of --folds' blocks: give --folds too")
    print("# rerun:", rerun_line("benchmarks/diagnose_recall.py", argv if argv is not None else sys.argv[1:]))
    try:
        items, classes = load_folders(args.data, limit=args.limit, frames=args.frames)
    except ValueError as e:
        ap.error(str(e))
    try:
        config = config_from(args.preset, None, args.sets, None)
    except ValueError as e:  # an unknown field, a bad value
        ap.error(str(e))
    run_for = _generators(ap, args, config)
    acc: dict[str, list[torch.Tensor]] = {s: [] for s in STAGES}
    labels, moderate, frame_of, folder_of, lost, crops = [], [], [], [], [], []
    for item in items:
        if len(item["boxes"]) == 0:
            continue
        best_item, details = stage_ious(run_for(item), item["image"], item["boxes"], lost_detail=args.lost)
        for k, v in best_item.items():
            acc[k].append(v)
        for d in details:
            g = d.pop("index")
            if args.show is not None:
                cls = classes[int(item["labels"][g])]
                crops.append((item["image"], item["boxes"][g].tolist(), d["nearest"],
                              _caption(d, cls, item["image_id"])))
            lost.append({"frame": item["image_id"], "folder": item["folder"], "class": classes[int(item["labels"][g])],
                         "box": [round(float(v), 1) for v in item["boxes"][g]],
                         "occluded": int(item["occluded"][g]), "truncated": round(float(item["truncated"][g]), 2),
                         **d})
        labels.append(item["labels"])
        moderate.append(kitti_difficulty_mask(item["boxes"], item["occluded"], item["truncated"]))
        frame_of += [item["image_id"]] * len(item["boxes"])
        folder_of += [item["folder"]] * len(item["boxes"])
    best = {k: torch.cat(v) if v else torch.zeros(0) for k, v in acc.items()}
    lab = torch.cat(labels) if labels else torch.zeros(0, dtype=torch.int64)
    mod = torch.cat(moderate) if moderate else torch.zeros(0, dtype=torch.bool)
    n = len(lab)
    preset = args.preset + "".join(f", {kv}" for kv in args.sets)
    if args.folds is not None:
        apart = ", whole drives" if args.whole_drives else ""
        preset += (f"; each frame ranked by a model fitted without its block ({args.folds} folds{apart}, "
                   f"seed {args.seed})")
    print(f"# {len(items)} frames, {n} objects ({int(mod.sum())} moderate), preset {preset}; "
          "recall (%) at IoU 0.7 unless named")
    splits = [("all", torch.ones(n, dtype=torch.bool))]
    for name, _ in folder_splits(items):  # each data folder, when there are several
        splits.append((name, torch.tensor([f == name for f in folder_of], dtype=torch.bool)))
    if len(args.frames) > 1:
        for r in args.frames:
            splits.append((r.text, torch.tensor([int(f) in r for f in frame_of], dtype=torch.bool)))
    record: dict = {"rerun": rerun_line("benchmarks/diagnose_recall.py", argv if argv is not None else sys.argv[1:]),
                    "preset": args.preset, "sets": args.sets, "folds": args.folds, "seed": args.seed,
                    "whole_drives": args.whole_drives,
                    "classes": list(classes), "splits": {}}
    for name, m in splits:
        table = stage_table({k: b[m] for k, b in best.items()}, lab[m], mod[m], classes)
        kind = "frames" if name.replace(":", "").isdigit() else "folder"
        title = f"# {kind} {name}: {int(m.sum())} objects" if name != "all" else f"# all frames: {n} objects"
        print(format_stage_table(title, table, lab[m], mod[m], classes))
        record["splits"][name] = {"num_objects": int(m.sum()), "frames": sorted({f for f, keep in zip(frame_of, m.tolist()) if keep}),
                                  "stages": table}
    if args.lost:
        print(format_lost(lost))
        record["lost"] = lost
    if args.show is not None:
        _write_sheet(args.show, crops, lost)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(record, indent=1))
        print(f"wrote {args.json}")
    return record


if __name__ == "__main__":
    main()
