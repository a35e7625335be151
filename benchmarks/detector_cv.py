"""Detector settings compared on every dev frame: whole-drives cross-validation, paired.

The frames of the given KITTI-format folders are split into ``--folds`` contiguous blocks.
For each block, the detector of each ``--arm`` (``reeb detector fit``'s options) is trained
on the other blocks less every frame of the block's drives and every near-copy of one of its
frames (:func:`reeb_torch.ranker.frames.training_frames`, as ``reeb fit --whole-drives`` holds
frames out), then run on the block. The arms' proposals rank with a model fitted on the same
training frames (``reeb fit``'s defaults; kept per fold under ``--work``), unless an arm asks
for ``--proposals training-free``: no frame is scored by a ranking or a detector that saw it.

Every frame is thus scored once per arm and seed, by detectors that never saw its drive, and
KITTI's 2D AP|R40 (moderate; :mod:`reeb_torch.metrics.kitti_ap`) is computed over all of them
together. The first arm is A; every other arm is B against it: each arm's AP (mean over
``--seeds``) with its frame-bootstrap interval, and the paired bootstrap's B − A
(:func:`~reeb_torch.metrics.kitti_ap.paired_bootstrap`: the same frames drawn for both arms),
over all frames and per folder.

    python benchmarks/detector_cv.py ../shared/data/kitti ../shared/data/kitti_tracking --folds 5 \\
        --arm base="" --arm narrow="--neck-channels 64 --head-width 256" --seeds 0 1 2 \\
        --out docs/results/detector/cv_narrow --work /tmp/detector_cv

Writes ``OUT/cv.txt`` (the tables) and ``OUT/cv.json`` (per arm its scores and per seed its
fits' times; per comparison per class ``a``, ``b``, ``diff``, intervals, ``share_b_better``,
``verdict``, and the same per folder; ``per_seed``: per comparison and class, each seed's
B − A over all frames and whether the seeds agree in sign, also under each comparison's
table: the bootstrap draws frames with the fits fixed, and two fits of one setting (another
seed, another CPU) differ by more than its interval; the command; the machine). With ``--work``, each
fold's ranking and each (arm, seed)'s detections are kept there and reused by a later run of
the same options; arms that differ only in detection settings (``--test-proposals``,
``--box-passes``) share their fitted heads there.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line  # noqa: E402
from detector_paired import _mean_scores, fit_options, parse_arm, parse_with_arms  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("roots", type=Path, nargs="+", help="labelled KITTI-format folders")
    p.add_argument("--arm", type=parse_arm, action="append", required=True, metavar='NAME="OPTIONS"',
                   help="a setting: reeb detector fit's options; the first is A, the baseline (two or more)")
    p.add_argument("--folds", type=int, default=5, help="blocks of frames held out in turn (default 5)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="S", help="fit seeds (default 0)")
    p.add_argument("--out", type=Path, required=True, help="folder for cv.txt and cv.json")
    p.add_argument("--work", type=Path, help="keep each fold's ranking and each arm's detections here")
    p.add_argument("--cache", type=Path, help="backbone-map and proposal cache [default: reeb's]")
    p.add_argument("--limit", type=int, help="only the first N frames of each folder")
    p.add_argument("--other-work", type=Path, metavar="DIR",
                   help="every arm's detections also read from this --work folder of the same command run "
                        "elsewhere (another machine or thread count), as arm NAME.other, paired with the rest")
    p.add_argument("--without-native-bf16", nargs="+", default=[], metavar="NAME",
                   help="these arms' detectors scored again as on a CPU without native bfloat16 "
                        "(REEB_NATIVE_BF16=0: the backbone in float32, the heads as trained), as arm NAME.nobf16")
    args = parse_with_arms(p, argv)
    given = dict(args.arm)
    unknown = [n for n in args.without_native_bf16 if n not in given]
    if unknown:
        p.error(f"--without-native-bf16: no arm named {', '.join(unknown)}")
    args.nobf16 = {f"{n}.nobf16" for n in args.without_native_bf16}
    args.arm += [(f"{n}.nobf16", given[n]) for n in args.without_native_bf16]
    if args.other_work is not None:
        args.other = {f"{n}.other": n for n, _ in args.arm}
        args.arm += [(f"{n}.other", o) for n, o in args.arm]
    else:
        args.other = {}
    return args


def training_sides(items: list[dict], folds: int) -> tuple[list[list[int]], list[list[int]]]:
    """The held-out blocks and, for each, the frames its models are fitted on (whole drives
    and near-copies of a held-out frame left out)."""
    from reeb_torch.ranker.frames import similar_frames, training_frames
    from reeb_torch.tuning import fold_blocks

    ids, folders = [it["image_id"] for it in items], [it["folder"] for it in items]
    blocks = fold_blocks(len(items), folds)
    similar = similar_frames([it["image"] for it in items])
    return blocks, [training_frames(blocks, f, ids, folders, similar, gap=len(ids)) for f in range(len(blocks))]


def fold_rankers(roots: list[Path], items: list[dict], train_sides: list[list[int]], work: Path | None,
                 limit: int | None, quiet: bool) -> list[str]:
    """Per fold, ranker weights fitted with ``reeb fit``'s defaults on its training frames
    (kept under ``work/rankers``, named by the frames, and reused)."""
    import tempfile

    from reeb_torch.config import ReebConfig
    from reeb_torch.ranker import frames as F
    from reeb_torch.ranker import fit as RF
    from reeb_torch.tuning import FrameCache
    from reeb_torch.ranker import save_ranker

    folder = (work or Path(tempfile.mkdtemp(prefix="detector-cv-"))) / "rankers"
    folder.mkdir(parents=True, exist_ok=True)
    keys = [f"{items[i]['folder']}/{items[i]['image_id']}" for i in range(len(items))]
    paths = [folder / f"fold{f}-{hashlib.sha256(' '.join(keys[i] for i in side).encode()).hexdigest()[:12]}"
             ".safetensors" for f, side in enumerate(train_sides)]
    if all(p.is_file() for p in paths):
        return [str(p) for p in paths]
    frames = F.load_fit_frames([str(r) for r in roots], limit=limit)
    if [f"{fo}/{i}" for fo, i in zip(frames.folders, frames.ids)] != keys:
        raise SystemExit("the ranking's frames are not the detector's (labels without images?)")
    cfg = ReebConfig()
    cache = FrameCache(frames)
    names = cache.candidates(cfg.unranked(), 0).feature_names
    opts = RF.FitOptions()
    samples = F.frame_samples(cache, cfg, opts)
    for f, (side, path) in enumerate(zip(train_sides, paths)):
        if not path.is_file():
            t0 = time.perf_counter()
            model = RF.fit_ranker([samples[i] for i in side], names, opts, frames.classes)
            save_ranker(model, path, {"frames": [keys[i] for i in side]}, cfg.to_dict())
            if not quiet:
                print(f"fold {f}: ranking fitted on {len(side)} frames in {time.perf_counter() - t0:.0f} s",
                      file=sys.stderr)
    return [str(p) for p in paths]


INFERENCE_ONLY = ("top_k_test", "box_passes", "box_head_rank", "box_head_int8")
"""The settings that change detection, not training: arms that differ only in them share
their fitted heads (kept under ``--work``)."""

UNKEYED = ("box_head_int8",)
"""Inference-only settings left out of the kept heads' key (heads kept before they existed
are found)."""


def _fold_detector(settings: Any, training: Any, o: dict[str, Any], proposals: str, side: list[int],
                   items: list[dict], args: argparse.Namespace,
                   nobf16: bool = False) -> tuple[Any, dict[str, Any] | None]:
    """The fold's detector with the arm's settings: its heads trained here, or read from a fit
    of the same training settings kept under ``--work`` (record None); with ``nobf16``, built
    as on a CPU without native bfloat16 (the backbone in float32, the same heads)."""
    import dataclasses

    from reeb_torch.detection import ReebDetector, proposal_settings
    from reeb_torch.detection.detector_file import read_detector_file
    from reeb_torch.detection.fitting import heads_frames, train_detector, tune_factorised
    from reeb_torch.config_text import parse_sets

    classes = tuple(c.strip() for c in o["classes"].split(",") if c.strip())
    changes = parse_sets(o.get("sets") or ())  # --set: REEB's settings over the proposals'
    top_k = max(settings.top_k_train, settings.top_k_test)  # REEB's top_k: the training proposals' too
    config = proposal_settings(proposals, top_k, changes)[0] if changes else None
    trained_as = dataclasses.replace(settings, **{k: getattr(type(settings)(), k) for k in INFERENCE_ONLY})
    full_training = dataclasses.replace(training, factorised_epochs=0)  # the passes after factorising come below
    trained_by = {k: v for k, v in dataclasses.asdict(full_training).items() if k != "factorised_epochs"}
    shape = {k: v for k, v in dataclasses.asdict(trained_as).items() if k not in UNKEYED}
    key = hashlib.sha256(json.dumps([shape, trained_by, classes, top_k,
                                     proposals, sorted(side), args.limit] + ([changes] if changes else []),
                                    default=str).encode()).hexdigest()[:16]
    kept = args.work / "detectors" / f"{key}.safetensors" if args.work else None
    full = dataclasses.replace(settings, box_head_rank=0, box_head_int8=False)  # the heads as trained (kept whole)
    if kept is not None and kept.is_file():
        det = ReebDetector(classes, proposals, full, config=config)
        det.model.load_state_dict(read_detector_file(kept)[0], strict=False)
        record = None
    else:
        t0 = time.perf_counter()
        det = train_detector(ReebDetector, [items[i] for i in side], args.roots, classes=classes, proposals=proposals,
                             settings=full, training=full_training, cache_dir=args.cache, progress=not args.quiet,
                             config=config)
        record = {"fit_s": round(time.perf_counter() - t0, 1), "train_heads_s": round(det.history["train_s"], 1),
                  "steps": det.history["steps"]}
        if kept is not None:
            kept.parent.mkdir(parents=True, exist_ok=True)
            det.save(kept)
    if nobf16 and det.precision != "float32":
        det = _without_native_bf16(det, classes, proposals, full, config)
    if settings.box_head_rank:
        t0 = time.perf_counter()
        frames = (heads_frames(det, [items[i] for i in side], training, args.cache, not args.quiet)
                  if training.factorised_epochs else [])
        try:
            tuned = tune_factorised(det, frames[:len(side)], settings.box_head_rank, training,
                                    progress=not args.quiet)
        finally:
            det.model.rpn.cache = None
        if tuned is not None:
            record = {"fit_s": round(time.perf_counter() - t0, 1), "train_heads_s": round(tuned["train_s"], 1),
                      "steps": tuned["steps"]}
    if settings.box_head_int8:
        det.quantise_box_head()
    return det.eval(), record


def _without_native_bf16(det: Any, classes: tuple[str, ...], proposals: str, settings: Any, config: Any) -> Any:
    """``det``'s trained heads on the backbone a CPU without native bfloat16 runs
    (``REEB_NATIVE_BF16=0`` while it is built: float32)."""
    import os
    import warnings

    from reeb_torch.detection import ReebDetector
    from reeb_torch.detection.detector_file import trained_keys

    before = os.environ.get("REEB_NATIVE_BF16")
    os.environ["REEB_NATIVE_BF16"] = "0"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "this CPU has no native bfloat16": the point
            cpu = ReebDetector(classes, proposals, settings, config=config)
    finally:
        if before is None:
            del os.environ["REEB_NATIVE_BF16"]
        else:
            os.environ["REEB_NATIVE_BF16"] = before
    cpu.model.load_state_dict(trained_keys(det.model.state_dict()), strict=False)
    return cpu


def detections_key(o: dict[str, Any], seed: int, rankers: list[str], args: argparse.Namespace,
                   nobf16: bool = False) -> str:
    """The name an arm's detections of one seed are kept under in ``--work/detections``: by the
    fit's options as parsed (a changed default is another arm), the folds and the rankings."""
    parsed = {k: v for k, v in sorted(o.items()) if k not in ("quiet", "cache_dir", "out", "overwrite")
              and not (k == "sets" and not v)}  # no --set: the key it had before the option
    return hashlib.sha256(json.dumps([parsed, seed, args.folds, args.limit, rankers] + (["nobf16"] if nobf16 else []),
                                     default=str).encode()).hexdigest()[:16]


def other_run(name: str, options: str, seed: int, rankers: list[str], args: argparse.Namespace) -> list[dict]:
    """An arm's detections of one seed from ``--other-work``: the same command run elsewhere
    (another machine, another thread count), its rankings in that folder."""
    import torch

    theirs = [str(args.other_work / "rankers" / Path(r).name) for r in rankers]
    path = args.other_work / "detections" / (
        f"{detections_key(fit_options(args.roots, options), seed, theirs, args, name in args.nobf16)}.pt")
    if not path.is_file():
        raise SystemExit(f"--other-work: no detections of arm {name}, seed {seed} in {path.parent} (run the same "
                         "command with --work there first)")
    return torch.load(path, weights_only=True)["detections"]


def run_arm(options: str, seed: int, items: list[dict], blocks: list[list[int]], sides: list[list[int]],
            rankers: list[str], args: argparse.Namespace, nobf16: bool = False) -> tuple[list[dict], dict[str, Any]]:
    """The detections of every frame by the arm's detectors (each trained without the frame's
    block), and the fits' record; kept under ``--work`` by options and seed."""
    import torch

    from reeb_torch.detection import TrainSettings, detect
    from reeb_torch.detection.fitting import cached_frames, crop_from_labels
    from reeb_torch.runs.detector import fit_settings

    o = fit_options(args.roots, options)
    kept = args.work / "detections" / f"{detections_key(o, seed, rankers, args, nobf16)}.pt" if args.work else None
    if kept is not None and kept.is_file():
        saved = torch.load(kept, weights_only=True)
        return saved["detections"], saved["record"]
    settings = fit_settings(o)
    training = TrainSettings(epochs=o["epochs"], seed=seed, hflip=o["hflip"], factorised_epochs=o["factorised_epochs"])
    detections: list[dict] = [{} for _ in items]
    record: dict[str, Any] = {"fit_s": [], "train_heads_s": [], "steps": []}
    for f, (block, side) in enumerate(zip(blocks, sides)):
        proposals = rankers[f] if o["proposals"] == "default" else o["proposals"]
        fold = settings if o["crop_top"] != "auto" else dataclasses.replace(
            settings, crop_top=crop_from_labels([items[i] for i in side]))  # from the fold's training labels
        det, fitted = _fold_detector(fold, training, o, proposals, side, items, args, nobf16)
        for k, v in (fitted or {"fit_s": 0.0, "train_heads_s": 0.0, "steps": 0}).items():
            record[k].append(v)
        try:
            found = detect(det.model, cached_frames(det, [items[i] for i in block], args.cache, not args.quiet),
                           progress=False, passes=det.settings.box_passes)
        finally:
            det.model.rpn.cache = None
        for i, d in zip(block, found):
            detections[i] = {k: v.detach().cpu() for k, v in d.items()}
    if kept is not None:
        kept.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"detections": detections, "record": record}, kept)
    return detections, record


def _subset(stats: dict[str, list], frames: list[int]) -> dict[str, list]:
    return {k: [v[i] for i in frames] for k, v in stats.items()}


def main(argv: list[str] | None = None) -> int:
    from reeb_torch.detection import format_paired, load_frames, paired_scores
    from reeb_torch.metrics import kitti_ap

    args = parse_args(argv)
    classes = {tuple(c.strip() for c in fit_options(args.roots, o)["classes"].split(",")) for _, o in args.arm}
    if len(classes) > 1:
        raise SystemExit("every arm must train the same classes")
    cls = next(iter(classes))
    items = load_frames(args.roots, cls, args.limit)
    blocks, sides = training_sides(items, args.folds)
    need_rankers = any(fit_options(args.roots, o)["proposals"] == "default" for _, o in args.arm)
    rankers = fold_rankers(args.roots, items, sides, args.work, args.limit, args.quiet) if need_rankers else []
    objects = [it["objects"] for it in items]
    folders = sorted({it["folder"] for it in items}, key=[it["folder"] for it in items].index)
    by_folder = {fo: [i for i, it in enumerate(items) if it["folder"] == fo] for fo in folders}
    arms: dict[str, dict[str, Any]] = {}
    stats: dict[str, list[Any]] = {}
    for name, options in args.arm:
        runs = []
        for seed in args.seeds:
            if name in args.other:
                dets = other_run(args.other[name], options, seed, rankers, args)
                record = {"fit_s": [0.0], "train_heads_s": [0.0], "steps": [0]}
            else:
                dets, record = run_arm(options, seed, items, blocks, sides, rankers, args, name in args.nobf16)
            st = kitti_ap.evaluate(objects, [{**d, "labels": d["labels"] - 1} for d in dets], cls)
            stats.setdefault(name, []).append(st)
            ap = {k: None if v != v else round(100 * v, 2) for k, v in kitti_ap.kitti_ap(st).items()}
            runs.append({"seed": seed, "ap": ap, **record})
            print(f"{name} seed {seed}: mAP {ap['mAP']} (fits {sum(record['fit_s']):.0f} s)", file=sys.stderr)
        base = {"objects": {c: sum(s.num_gt for s in stats[name][0][c]) for c in cls}, "frames": len(items),
                "training_frames": 0}
        arms[name] = {"options": options, **_mean_scores([base], stats[name], args.samples, args.seed),
                      "runs": runs}
    first = args.arm[0][0]
    comparisons: dict[str, Any] = {}
    seeds: dict[str, Any] = {}
    for name, _ in args.arm[1:]:
        key = f"{name} vs {first}"
        seeds[key] = seed_differences(arms[first]["runs"], arms[name]["runs"])
        comparisons[key] = {"all": paired_scores(kitti_ap.paired_bootstrap(stats[first], stats[name],
                                                                           samples=args.samples, seed=args.seed))}
        for fo, idx in by_folder.items():
            comparisons[key][fo] = paired_scores(kitti_ap.paired_bootstrap(
                [_subset(s, idx) for s in stats[first]], [_subset(s, idx) for s in stats[name]],
                samples=args.samples, seed=args.seed))
    command = rerun_line("benchmarks/detector_cv.py", sys.argv[1:] if argv is None else argv)
    lines = [f"# rerun: {command}", f"# machine: {json.dumps(environment(), sort_keys=True)}",
             f"# {len(items)} frames in {args.folds} blocks; each scored by detectors (and rankings) fitted "
             f"without its block's drives; seeds {' '.join(map(str, args.seeds))}", ""]
    for name, a in arms.items():
        lines.append(f"## arm {name}: reeb detector fit {a['options'] or '(defaults)'}")
        for r in a["runs"]:
            aps = ", ".join(f"{k} {'-' if v is None else f'{v:.1f}'}" for k, v in r["ap"].items())
            lines.append(f"seed {r['seed']}: {aps}; fits {sum(r['fit_s']):.0f} s "
                         f"({sum(r['train_heads_s']):.0f} s of head training)")
        lines += [_score_table(a), ""]
    for key, c in comparisons.items():
        b, a = key.split(" vs ")
        for part, table in c.items():
            lines += [f"## paired: {key}, {'all frames' if part == 'all' else part} ({args.samples} draws)",
                      format_paired(table, a, b)]
            if part == "all":
                lines.append(seed_line(seeds[key]))
            lines.append("")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cv.txt").write_text("\n".join(lines))
    (args.out / "cv.json").write_text(json.dumps(
        {"command": command, "roots": list(map(str, args.roots)), "folds": args.folds, "seeds": args.seeds,
         "arms": arms, "comparisons": comparisons, "per_seed": seeds, "samples": args.samples, "environment": environment(),
         "options": {n: shlex.split(o) for n, o in args.arm}}, indent=2) + "\n")
    print("\n".join(lines))
    return 0


def seed_differences(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per class, B − A of each seed's AP over all frames (``a``, ``b``: the arms' runs, seed
    by seed, each with its ``"ap"``) and whether every seed's difference has the same sign:
    the paired bootstrap draws frames with the fits fixed, and two fits of one setting differ
    by more than its interval, so a difference the seeds do not agree on is not a result."""
    out: dict[str, dict[str, Any]] = {}
    for c in a[0]["ap"]:
        diffs = [None if ra["ap"][c] is None or rb["ap"][c] is None else round(rb["ap"][c] - ra["ap"][c], 2)
                 for ra, rb in zip(a, b)]
        known = [d for d in diffs if d is not None]
        out[c] = {"per_seed": diffs, "seeds_agree": len(known) > 1 and (all(d > 0 for d in known)
                                                                          or all(d < 0 for d in known))}
    return out


def seed_line(diffs: dict[str, dict[str, Any]]) -> str:
    """``per seed, B − A: Car +1.0 / −0.5 (seeds disagree), ...`` of :func:`seed_differences`."""
    parts = []
    for c, d in diffs.items():
        values = " / ".join("-" if v is None else f"{v:+.1f}" for v in d["per_seed"])
        verdict = "" if len(d["per_seed"]) < 2 else " (seeds agree)" if d["seeds_agree"] else " (seeds disagree)"
        parts.append(f"{c} {values}{verdict}")
    return "per seed, B - A: " + ", ".join(parts)


def _score_table(a: dict[str, Any]) -> str:
    from reeb_torch.detection import format_scores

    return format_scores(a)


if __name__ == "__main__":
    raise SystemExit(main())
