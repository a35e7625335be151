"""Two or more detector settings on the same held-out frames, compared by the paired frame bootstrap.

Each ``--arm NAME="OPTIONS"`` is a ``reeb detector fit`` with those options (as the command
takes them: ``--min-size 384``, ``--test-proposals 2000``, ``--hflip``, ``--proposals FILE``,
...), trained on the ``--train`` folders with the same seed, then scored on the ``--val``
folders with KITTI's 2D AP|R40 (moderate; :mod:`reeb_torch.metrics.kitti_ap`). The first arm is
A; every other arm is B against it: each arm's AP per class and mAP with its frame-bootstrap
interval, and :func:`~reeb_torch.metrics.kitti_ap.paired_bootstrap`'s B - A (the same frames
drawn for both arms), its 95 % interval and the share of draws where B wins. With ``--seeds`` every arm is fitted once per
seed and an arm's AP is its mean over them, on every draw as on all frames.

The arms share one cache (``--cache``): the backbone's maps are kept per input size (arms of
one ``--min-size``/``--max-size`` share them) and REEB's proposals per proposal setting, so
only the first arm of a size pays for the backbone. With ``--work DIR`` each arm's detector
is kept there (``NAME.safetensors``) and a later run loads it instead of fitting again when it
was made by the same command.

    python benchmarks/detector_paired.py --train ../shared/data/kitti --val ../shared/data/kitti_tracking \\
        --arm 576="--proposals docs/results/ranker/kitti_only.safetensors" \\
        --arm 375="--proposals docs/results/ranker/kitti_only.safetensors --min-size 375" \\
        --out docs/results/detector/min_size --work /tmp/arms

Writes ``OUT/paired.txt`` (the tables) and ``OUT/paired.json`` (each arm's scores, settings and
``runs``: each seed's scores and timings; each comparison per class: ``a``, ``b``, ``diff``, their intervals,
``share_b_better``, ``verdict``; the command; the machine).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line  # noqa: E402

FORBIDDEN = ("--val", "--limit", "--cache", "-o", "--out", "--overwrite")
"""Options the benchmark sets for every arm itself."""


def parse_arm(text: str) -> tuple[str, str]:
    """``NAME=OPTIONS`` -> ``(name, options)``."""
    name, sep, options = text.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z0-9_.+-]+", name):
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=\"reeb detector fit options\" "
                                         "(NAME of letters, digits, . _ + -)")
    used = [w for w in shlex.split(options) if w.split("=")[0] in FORBIDDEN]
    if used:
        raise argparse.ArgumentTypeError(f"arm {name}: {', '.join(used)} is the benchmark's own option")
    return name, options


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", type=Path, nargs="+", required=True, metavar="DIR", help="KITTI-format folders to fit on")
    p.add_argument("--val", type=Path, nargs="+", required=True, metavar="DIR", help="KITTI-format folders to score on")
    p.add_argument("--arm", type=parse_arm, action="append", required=True, metavar='NAME="OPTIONS"',
                   help="a setting: reeb detector fit's options; the first is A, the baseline (two or more)")
    p.add_argument("--out", type=Path, required=True, help="folder for paired.txt and paired.json")
    p.add_argument("--work", type=Path, help="keep each arm's detector here, and reuse one made by the same command")
    p.add_argument("--cache", type=Path, help="backbone-map and proposal cache [default: reeb's]")
    p.add_argument("--limit", type=int, help="only the first N frames of each folder (train and val)")
    p.add_argument("--seeds", type=int, nargs="+", metavar="S",
                   help="fit every arm with each of these seeds and compare the arms' mean AP over them "
                        "(default: each arm's own --seed, once)")
    return parse_with_arms(p, argv)


def parse_with_arms(p: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``p``'s arguments with the options every paired benchmark shares (``--samples``,
    ``--seed``, ``-q``), checked for two or more arms of distinct names (``--arm``, and those
    scored again ``--without-native-bf16`` where the benchmark has that option)."""
    p.add_argument("--samples", type=int, default=1000, help="bootstrap draws")
    p.add_argument("--seed", type=int, default=0, help="the bootstrap's seed")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    args = p.parse_args(argv)
    names = [n for n, _ in args.arm]
    if len(args.arm) + len(getattr(args, "without_native_bf16", [])) < 2 or len(set(names)) != len(names):
        p.error(f"give two or more --arm with distinct names (got {names})")
    return args


def fit_options(train: list[Path], options: str) -> dict[str, Any]:
    """``reeb detector fit``'s parameters for ``train`` and ``options``, as the command parses them."""
    import click

    from reeb_torch.runs.detector import fit

    try:
        with fit.make_context("fit", [*map(str, train), *shlex.split(options)]) as ctx:
            return dict(ctx.params)
    except click.ClickException as e:
        raise SystemExit(f"arm options {options!r}: {e.format_message()}") from None


def seed_runs(name: str, options: str, seeds: list[int] | None, train: list[Path]) -> list[tuple[str, str, int]]:
    """The fits of one arm: ``(file stem, options, seed)`` per seed; the arm's own seed keeps
    the arm's name and options (so a detector kept from a run without ``--seeds`` is reused)."""
    own = fit_options(train, options)["seed"]
    return [(name, options, own) if s == own else (f"{name}-seed{s}", f"{options} --seed {s}".strip(), s)
            for s in (seeds or [own])]


def fit_arm(stem: str, options: str, args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """The detector of these options (fitted, or loaded from ``--work``) and its fit record."""
    from reeb_torch.detection import ReebDetector
    from reeb_torch.config_text import parse_sets
    from reeb_torch.runs.detector import fit_settings

    o = fit_options(args.train, options)
    auto_crop = o["crop_top"] == "auto"
    settings = fit_settings(o)
    command = " ".join(["reeb detector fit", *map(shlex.quote, map(str, args.train)), options]
                       + (["--limit", str(args.limit)] if args.limit else [])).strip()
    kept = args.work / f"{stem}.safetensors" if args.work else None
    if kept is not None and kept.is_file():
        det = ReebDetector.load(kept)
        same = {k: v for k, v in vars(det.settings).items() if not (auto_crop and k == "crop_top")} == {
            k: v for k, v in vars(settings).items() if not (auto_crop and k == "crop_top")}  # the defaults then too
        if det.meta.get("provenance", {}).get("command") == command and same:
            print(f"{stem}: {kept} made by the same command; not fitted again", file=sys.stderr)
            record = kept.with_suffix(".json")
            return det, {**(json.loads(record.read_text()) if record.is_file() else {}), "reused": str(kept)}
    names = tuple(c.strip() for c in o["classes"].split(",") if c.strip())
    t0 = time.perf_counter()
    det = ReebDetector.fit(args.train, classes=names, proposals=o["proposals"], epochs=o["epochs"], seed=o["seed"],
                           settings=settings, cache_dir=args.cache, limit=args.limit, hflip=o["hflip"],
                           auto_crop=auto_crop, progress=not args.quiet, command=command,
                           proposal_changes=parse_sets(o["sets"]) or None)
    record = {"fit_s": round(time.perf_counter() - t0, 1), "train_heads_s": round(det.history["train_s"], 1),
              "steps": det.history["steps"]}
    if kept is not None:
        kept.parent.mkdir(parents=True, exist_ok=True)
        det.save(kept)
        kept.with_suffix(".json").write_text(json.dumps(record) + "\n")
    return det, record


def _mean_scores(runs: list[dict[str, Any]], stats: list[Any], samples: int, seed: int) -> dict[str, Any]:
    """An arm's AP (mean over its seeds) with the frame-bootstrap interval of that mean."""
    from reeb_torch.metrics.kitti_ap import bootstrap, kitti_ap

    def pct(v: float) -> float | None:
        return None if math.isnan(v) else round(100 * v, 2)

    aps = [kitti_ap(s) for s in stats]
    mean = {k: sum(a[k] for a in aps) / len(aps) for k in aps[0]}
    interval = bootstrap(stats, samples=samples, seed=seed)
    return {"ap": {k: pct(v) for k, v in mean.items()},
            "interval_95": {k: [pct(lo), pct(hi)] for k, (lo, hi) in interval.items()},
            "objects": runs[0]["objects"], "frames": runs[0]["frames"],
            "training_frames": runs[0]["training_frames"]}


def _arm_lines(name: str, a: dict[str, Any], args: argparse.Namespace) -> list[str]:
    from reeb_torch.detection import format_scores

    n_val = a["frames"]
    lines = [f"## arm {name}: reeb detector fit {' '.join(map(str, args.train))} {a['options']}"]
    for r in a["runs"]:
        timing = (f"fit {r['fit_s']:.0f} s ({r['train_heads_s']:.0f} s of head training, {r['steps']} steps)"
                  if "fit_s" in r else "fitted before")
        timing += f", kept as {r['reused']}" if "reused" in r else ""
        aps = ", ".join(f"{k} {'-' if v is None else f'{v:.1f}'}" for k, v in r["ap"].items())
        lines.append(f"seed {r['seed']}: {aps}; {timing}; scoring from the cache {r['val_s']:.0f} s")
    seeds = f"mean of {len(a['runs'])} seeds, " if len(a["runs"]) > 1 else ""
    lines += [f"KITTI 2D AP|R40 (moderate; {seeds}95 % frame-bootstrap interval) on {n_val} frames of "
              f"{' '.join(map(str, args.val))}:", format_scores(a), ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    from reeb_torch.detection import detector_stats, format_paired, paired_scores, scores_of
    from reeb_torch.metrics.kitti_ap import kitti_ap, paired_bootstrap

    args = parse_args(argv)
    arms: dict[str, dict[str, Any]] = {}
    stats: dict[str, list[Any]] = {}
    for name, options in args.arm:
        runs = []
        for stem, opts, seed in seed_runs(name, options, args.seeds, args.train):
            det, record = fit_arm(stem, opts, args)
            t0 = time.perf_counter()
            items, st = detector_stats(det, args.val, limit=args.limit, cache_dir=args.cache, progress=not args.quiet)
            record["val_s"] = round(time.perf_counter() - t0, 1)
            stats.setdefault(name, []).append(st)
            runs.append({"seed": seed, "options": opts, **record,
                         **scores_of(det, items, st, samples=args.samples, seed=args.seed)})
            print(f"{stem}: mAP {runs[-1]['ap']['mAP']}", file=sys.stderr)
        arms[name] = {"options": options, "settings": det.metadata()["settings"], "proposals": det.proposals["spec"],
                      **_mean_scores(runs, stats[name], args.samples, args.seed), "runs": runs}
    first = args.arm[0][0]
    comparisons = {}
    for name, _ in args.arm[1:]:
        c = paired_scores(paired_bootstrap(stats[first], stats[name], samples=args.samples, seed=args.seed))
        per_seed = [100 * (kitti_ap(b)["mAP"] - kitti_ap(a)["mAP"]) for a, b in zip(stats[first], stats[name])]
        comparisons[f"{name} vs {first}"] = {**c, "mAP_diff_per_seed": [round(d, 2) for d in per_seed]}
    command = rerun_line("benchmarks/detector_paired.py", sys.argv[1:] if argv is None else argv)
    env = environment()
    lines = [f"# rerun: {command}", f"# machine: {json.dumps(env, sort_keys=True)}", ""]
    for name, a in arms.items():
        lines += _arm_lines(name, a, args)
    n_val = next(iter(arms.values()))["frames"]
    for key, c in comparisons.items():
        b, a = key.split(" vs ")
        table = {k: v for k, v in c.items() if k != "mAP_diff_per_seed"}
        seeds = f", the {len(c['mAP_diff_per_seed'])} seeds' mean AP on each draw" if len(stats[first]) > 1 else ""
        lines += [f"## paired: {key} ({args.samples} draws of the {n_val} frames{seeds})", format_paired(table, a, b)]
        if len(c["mAP_diff_per_seed"]) > 1:
            lines.append("mAP B - A per seed: " + ", ".join(f"{d:+.1f}" for d in c["mAP_diff_per_seed"]))
        lines.append("")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "paired.txt").write_text("\n".join(lines))
    (args.out / "paired.json").write_text(json.dumps(
        {"command": command, "train": list(map(str, args.train)), "val": list(map(str, args.val)),
         "arms": arms, "comparisons": comparisons, "samples": args.samples, "environment": env}, indent=2) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
