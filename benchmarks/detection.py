"""Detection AP on KITTI of one detector per proposal source: REEB against the alternatives.

For each source named in ``--proposals`` this trains a Faster R-CNN on a frozen, pretrained
EfficientNet-Lite0 (:func:`reeb_torch.detection.reeb_fasterrcnn_lite0`; the ``detect``
extra) on the ``--train`` folders and scores it on the ``--test`` folders with KITTI's 2D
AP|R40 (moderate; IoU 0.7 Car, 0.5 Pedestrian and Cyclist; :mod:`reeb_torch.metrics.kitti_ap`)
and frame-bootstrap intervals. Sources: ``reeb`` (``ProposalGenerator()``, the package
default), ``training-free`` (the preset of that name, when it exists), ``edgeboxes``,
``selective-search`` (OpenCV contrib) and ``rpn`` (a learned RPN on the same features, the
control). Every arm has the same network, initial weights, budget and seed.

The backbone's maps and every source's proposals are computed once per frame and cached
under ``--cache`` (default ``~/.cache/reeb-torch/detection``; stale entries are refused and
recomputed), so only the heads train: a few minutes per arm on two CPU cores.

    python benchmarks/detection.py --train ../shared/data/kitti --test ../shared/data/kitti_tracking \\
        --proposals reeb edgeboxes selective-search rpn --out docs/results/detection/kitti_to_tracking

Writes ``OUT/detection.json`` (``{"<name>": {"Car": ap, "Pedestrian": ap, "Cyclist": ap,
"mAP": ap, "train_s": s}}``, AP in percent) and ``OUT/detection_details.json`` (intervals,
proposal recall, settings, timings, the machine, the command).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line  # noqa: E402
from _detection_sources import SourceGenerator, SourceUnavailable, cached_proposals, make_source  # noqa: E402

ARMS = ("reeb", "training-free", "edgeboxes", "selective-search", "rpn")
CLASSES = ("Car", "Pedestrian", "Cyclist")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", type=Path, nargs="+", required=True, metavar="DIR", help="KITTI-format folders to train on")
    p.add_argument("--test", type=Path, nargs="+", required=True, metavar="DIR", help="KITTI-format folders to score on")
    p.add_argument("--proposals", nargs="+", default=list(ARMS), choices=ARMS, metavar="NAME",
                   help=f"proposal sources, among {', '.join(ARMS)} (default: all)")
    p.add_argument("--out", type=Path, required=True, help="folder for detection.json")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "reeb-torch" / "detection",
                   help="per-frame cache of backbone maps and proposals")
    p.add_argument("--epochs", type=int, default=12)
    p.add_argument("--max-steps", type=int, default=None, help="stop each arm's training after this many steps")
    p.add_argument("--batch-size", type=int, default=2, help="frames per step")
    p.add_argument("--lr", type=float, default=3e-4, help="AdamW's peak learning rate")
    p.add_argument("--rois", type=int, default=256, help="RoIs sampled per image for the box head's loss")
    p.add_argument("--proposals-train", type=int, default=2000, help="proposals per image in training")
    p.add_argument("--proposals-test", type=int, default=1000, help="proposals per image in testing")
    p.add_argument("--min-size", type=int, default=576, help="shorter side of the resized input")
    p.add_argument("--max-size", type=int, default=2048, help="bound on the longer side")
    p.add_argument("--limit", type=int, default=None, help="only the first N frames of each folder")
    p.add_argument("--bootstrap", type=int, default=1000, help="frame-bootstrap draws for the intervals")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hflip", action="store_true",
                   help="train on each frame's mirror image half of the time (its maps and proposals are cached too)")
    p.add_argument("--ranker", default=None, metavar="WEIGHTS",
                   help="the learned ranking's weights for the reeb arm (default: the shipped model; on frames "
                        "it was fitted on, as the dev folders, give weights `reeb fit` fitted on --train alone)")
    return p.parse_args(argv)


# -- data ---------------------------------------------------------------------------------


def load_frames(roots: list[Path], limit: int | None) -> list[dict[str, Any]]:
    """Every frame of the folders (:func:`reeb_torch.detection.load_frames`: ``image``, the
    three classes' ``boxes`` and ``labels`` 1..3, ``objects`` for the AP, ``ignore``,
    ``dontcare``); a folder without labels ends the run with its one-line reason."""
    from reeb_torch.detection import load_frames as read_frames

    try:
        return read_frames(roots, CLASSES, limit)
    except ValueError as e:
        raise SystemExit(str(e)) from None


def cached_frames(model: torch.nn.Module, items: list[dict], args: argparse.Namespace) -> list:
    """The items with their backbone maps (:func:`frozen_features`, cached)."""
    from reeb_torch.detection import CachedFrame, FeatureCache, frozen_features, weights_digest

    cache = FeatureCache(args.cache, weights_digest(), args.min_size, args.max_size)
    feats = frozen_features(model, items, cache)
    return [CachedFrame(it["image"], f, it["boxes"], it["labels"], it["ignore"], it["dontcare"])
            for it, f in zip(items, feats)]


# -- one arm ------------------------------------------------------------------------------


def build_model(name: str, args: argparse.Namespace, items: list[dict]) -> tuple[torch.nn.Module, float, str]:
    """The arm's detector (same seed, same initial weights for every arm), the seconds spent
    computing its source's proposals for ``items`` (~0 when all were cached) and the source's
    key (its settings: the REEB config's fingerprint, the baseline's settings)."""
    from reeb_torch.detection import reeb_fasterrcnn_lite0

    generator, proposal_s, key = None, 0.0, "learned"
    if name != "rpn":
        source = make_source(name, args.ranker)  # SourceUnavailable: the caller skips the arm
        t0 = time.perf_counter()
        cached_proposals(items, source, args.cache)
        proposal_s = time.perf_counter() - t0
        generator, key = SourceGenerator(source, args.cache), source.key
    torch.manual_seed(args.seed)
    model = reeb_fasterrcnn_lite0(
        len(CLASSES) + 1, proposals="learned" if name == "rpn" else "reeb", generator=generator,
        min_size=args.min_size, max_size=args.max_size,
        top_k_train=args.proposals_train, top_k_test=args.proposals_test,
        box_batch_size_per_image=args.rois, box_score_thresh=0.01, box_detections_per_img=100)
    return model, proposal_s, key


def test_proposals(model: torch.nn.Module, frames: list) -> tuple[list, list]:
    """Detections of every test frame and the proposals the box head saw (input pixels)."""
    from torchvision.models.detection.transform import resize_boxes

    from reeb_torch.detection import ReebRPN, detect

    seen: list[torch.Tensor] = []
    hook = model.rpn.register_forward_hook(lambda m, inp, out: seen.append(out[0][0].detach()))
    try:
        detections = detect(model, frames)
    finally:
        hook.remove()
    if isinstance(model.rpn, ReebRPN):  # REEB's boxes go to the heads without the RPN's forward
        model.rpn.eval()
        seen = [model.rpn.place(model.rpn.propose([f.image])[0], f.features.original_size, f.features.image_size)
                for f in frames]
    proposals = [resize_boxes(p, list(f.features.image_size), list(f.features.original_size))
                 for p, f in zip(seen, frames)]
    return detections, proposals


def proposal_recall(proposals: list, items: list[dict]) -> dict[str, float]:
    """Recall at IoU 0.7 and 0.5 of the test proposals, over the KITTI-moderate objects."""
    from reeb_torch.metrics.recall import kitti_difficulty_mask, recall_table, select_objects

    masks = [kitti_difficulty_mask(it["boxes"], it["occluded"], it["truncated"]) for it in items]
    gts, _ = select_objects([it["boxes"] for it in items], None, masks)
    k = max(1, max((len(p) for p in proposals), default=1))
    r = recall_table(proposals, gts, ks=(k,), ious=(0.5, 0.7))
    return {"k": k, "iou_0.5": float(r.micro[0, 0]), "iou_0.7": float(r.micro[0, 1])}


def score(detections: list, items: list[dict], samples: int, seed: int) -> dict[str, Any]:
    """AP|R40 (percent) per class and mAP, and their bootstrap intervals."""
    from reeb_torch.metrics import kitti_ap

    dets = [{**d, "labels": d["labels"] - 1} for d in detections]
    stats = kitti_ap.evaluate([it["objects"] for it in items], dets, CLASSES)
    ap = kitti_ap.kitti_ap(stats)
    interval = kitti_ap.bootstrap(stats, samples=samples, seed=seed)
    pct = lambda v: round(100 * v, 2) if not math.isnan(v) else None  # noqa: E731
    return {"ap": {k: pct(v) for k, v in ap.items()},
            "interval_95": {k: [pct(lo), pct(hi)] for k, (lo, hi) in interval.items()},
            "objects": {c: sum(s.num_gt for s in stats[c]) for c in CLASSES}}


def run_arm(name: str, train: list[dict], test: list[dict], args: argparse.Namespace) -> dict[str, Any]:
    """Train the arm's heads on ``train``, score it on ``test``."""
    from reeb_torch.detection import TrainSettings, train_heads

    from reeb_torch.detection import mirrored

    mirrors = [mirrored(it) for it in train] if args.hflip else []
    model, proposal_s, key = build_model(name, args, train + mirrors + test)
    t0 = time.perf_counter()
    train_frames, test_frames = cached_frames(model, train, args), cached_frames(model, test, args)
    for frame, mirror in zip(train_frames, cached_frames(model, mirrors, args) if mirrors else []):
        frame.mirror = mirror
    features_s = time.perf_counter() - t0
    settings = TrainSettings(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                             max_steps=args.max_steps, hflip=args.hflip)
    history = train_heads(model, train_frames, settings)
    t0 = time.perf_counter()
    detections, proposals = test_proposals(model, test_frames)
    test_s = time.perf_counter() - t0
    return {**score(detections, test, args.bootstrap, args.seed),
            "proposal_recall": proposal_recall(proposals, test), "source_key": key,
            "train_s": round(history["train_s"], 1), "steps": history["steps"],
            "final_loss": sum(history["losses"][-20:]) / len(history["losses"][-20:]),
            "proposal_s": round(proposal_s, 1), "features_s": round(features_s, 1), "test_s": round(test_s, 1)}


# -- report -------------------------------------------------------------------------------


def format_table(results: dict[str, dict]) -> str:
    """AP per class (with the 95 % interval), mAP, recall of the proposals, train time."""
    head = f"{'proposals':<18}" + "".join(f"{c:>22}" for c in (*CLASSES, "mAP")) + f"{'R@.7':>7}{'train s':>9}"
    lines = [head, "-" * len(head)]
    for name, r in results.items():
        cells = []
        for c in (*CLASSES, "mAP"):
            ap, (lo, hi) = r["ap"][c], r["interval_95"][c]
            cells.append("-".rjust(22) if ap is None else f"{ap:6.1f} [{lo:5.1f}, {hi:5.1f}]".rjust(22))
        rec = 100 * r["proposal_recall"]["iou_0.7"]
        lines.append(f"{name:<18}" + "".join(cells) + f"{rec:7.1f}{r['train_s']:9.0f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, dict]:
    args = parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    train, test = load_frames(args.train, args.limit), load_frames(args.test, args.limit)
    print(f"train: {len(train)} frames, {sum(len(t['boxes']) for t in train)} objects; "
          f"test: {len(test)} frames; cache {args.cache}")
    results: dict[str, dict] = {}
    for name in args.proposals:
        print(f"\n== {name}")
        try:
            results[name] = run_arm(name, train, test, args)
            print(format_table({name: results[name]}).splitlines()[-1])
        except SourceUnavailable as e:
            print(f"skipped: {e}")
    table = format_table(results)
    print("\nKITTI 2D AP|R40, moderate (%; 95 % frame-bootstrap interval), recall of the test "
          f"proposals at IoU 0.7 (moderate), head training seconds\n{table}")
    write(args, argv, results, table, len(train), len(test))
    return results


def write(args: argparse.Namespace, argv: list[str], results: dict, table: str, n_train: int, n_test: int) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {n: {**{c: r["ap"][c] for c in (*CLASSES, "mAP")}, "train_s": r["train_s"]} for n, r in results.items()}
    (args.out / "detection.json").write_text(json.dumps(summary, indent=2) + "\n")
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    settings["train"], settings["test"] = [str(p) for p in args.train], [str(p) for p in args.test]
    details = {"command": rerun_line("benchmarks/detection.py", argv), "train_frames": n_train,
               "test_frames": n_test, "settings": settings, "arms": results, "environment": environment()}
    (args.out / "detection_details.json").write_text(json.dumps(details, indent=2) + "\n")
    (args.out / "detection.txt").write_text(f"{details['command']}\n\n{table}\n")
    print(f"written: {args.out / 'detection.json'}, detection_details.json, detection.txt")


if __name__ == "__main__":
    main()
