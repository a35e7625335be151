"""A few labelled frames of another drive: fine-tune a model (``reeb fit --init``) or fit from scratch?

The user's case: a model fitted elsewhere and a handful of labelled frames of their own
camera. For each ordered pair of folders (source, target): a base model fitted on all of
the source; ``k`` consecutive frames of the target (its first ``k`` and its last ``k``, in
folder order) to adapt with; the other frames of the target, away from those (no frame of
their drive within ``--gap`` of them, none that looks nearly the same:
:func:`reeb_torch.ranker.frames.training_frames`), to test on. On the test frames, recall at
2000 proposals / IoU 0.7 of:

* ``training-free``: REEB alone;
* ``base``: the source's model as it is;
* ``scratch``: a model fitted on the ``k`` frames alone (``reeb fit``);
* ``fine-tuned``: the base model fine-tuned on the ``k`` frames (``reeb fit --init``);

and, for the three models, how often the class hint of each found object's best proposal
names its class.

Per fit seed and adapt block, then per direction over the seeds: fine-tuning's recall
minus each other's, averaged over the seeds, with a 95 % bootstrap interval over the
(block, test frame) units, and how many seeds it finds more objects with (sign test).

    python benchmarks/adapt.py --k 5 10 --seeds 0 1 2 3 4 --out docs/results/ranker/adapt

Beside ``adapt.txt`` and ``adapt.json`` it draws ``adapt.png`` (with matplotlib, the
``extras`` extra): each scenario's mean recall per condition, and fine-tuning's paired
differences with their intervals. ``--plot adapt.json`` redraws it from a saved record.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, environment, rerun_line, write_outputs  # noqa: E402

from reeb_torch import ReebConfig  # noqa: E402
from reeb_torch.ranker import frames as F  # noqa: E402
from reeb_torch.ranker import fit as RF  # noqa: E402
from reeb_torch.ranker import cv as fit_cv  # noqa: E402
from reeb_torch.metrics.recall import object_hits, sign_test  # noqa: E402
from reeb_torch.tuning import FrameCache  # noqa: E402
from reeb_torch.ranker import save_ranker  # noqa: E402

CONDITIONS = ("training-free", "base", "scratch", "fine-tuned")


def scenarios(frames: F.FitFrames, ks: list[int], gap: int) -> list[dict]:
    """Per ordered pair of folders and ``k``: the source frames, the first and the last ``k``
    frames of the target, and the target frames away from each."""
    folders = list(dict.fromkeys(frames.folders))
    similar = F.similar_frames(frames.images)
    out = []
    for src in folders:
        for dst in folders:
            if src == dst:
                continue
            source = [i for i, f in enumerate(frames.folders) if f == src]
            target = [i for i, f in enumerate(frames.folders) if f == dst]
            for k in ks:
                for where, adapt in (("first", target[:k]), ("last", target[-k:])):
                    rest = [i for i in target if i not in adapt]
                    test = F.training_frames([adapt, rest], 0, frames.ids, frames.folders, similar, gap)
                    out.append({"name": f"{Path(src).name} -> {Path(dst).name}, {where} {k}",
                                "direction": f"{Path(src).name} -> {Path(dst).name}", "source": source,
                                "adapt": adapt, "test": test})
    return out


def run_seed(cache: FrameCache, cfg: ReebConfig, scens: list[dict], seed: int, tmp: Path) -> dict[str, dict]:
    """Per scenario, per condition: the test objects' hits (``bool [N]``, frames in order),
    and under ``"hints"``, per condition with a class head, ``(right, found)``: of the test
    objects it finds, how many its best proposal's class hint names rightly."""
    frames = cache.frames
    opts = RF.FitOptions(seed=seed)
    samples = F.frame_samples(cache, cfg, opts)
    names = cache.candidates(cfg.unranked(), 0).feature_names
    bases: dict[tuple, Path] = {}
    out = {}

    def hits(ranker: str, test: list[int], hints: dict, name: str) -> torch.Tensor:
        outputs = cache.outputs(cfg.replace(ranker=ranker), test)
        gts = [frames.gts[i] for i in test]
        if ranker != "none":
            hinted = torch.cat(fit_cv.hinted_classes(outputs, gts))
            truth = torch.cat([frames.labels[i] for i in test])
            hints[name] = (int((hinted == truth).sum()), int((hinted >= 0).sum()))
        return torch.cat(object_hits([o["boxes"] for o in outputs], gts, 2000, 0.7))

    for s in scens:
        key = tuple(s["source"])
        if key not in bases:
            model = RF.fit_ranker([samples[i] for i in s["source"]], names, opts, frames.classes)
            bases[key] = save_ranker(model, tmp / f"base{len(bases)}_{seed}.safetensors")
        adapt = [samples[i] for i in s["adapt"]]
        tag = f"{len(out)}_{seed}"  # a file of its own: a generator reads its weights once
        scratch = save_ranker(RF.fit_ranker(adapt, names, opts, frames.classes), tmp / f"scratch{tag}.safetensors")
        tuned = RF.fit_ranker(adapt, names, dataclasses.replace(opts, init=str(bases[key])), frames.classes)
        tuned_path = save_ranker(tuned, tmp / f"tuned{tag}.safetensors")
        hints: dict = {}
        out[s["name"]] = {c: hits(r, s["test"], hints, c) for c, r in
                          zip(CONDITIONS, ("none", str(bases[key]), str(scratch), str(tuned_path)))}
        out[s["name"]]["hints"] = hints
    return out


def paired_difference(frames: F.FitFrames, per_seed: list[dict], scens: list[dict], other: str,
                      draws: int = 2000) -> dict:
    """Fine-tuned against ``other`` over the scenarios ``scens``: the difference in recall
    (points) averaged over the seeds, its 95 % bootstrap interval over (block, frame) units,
    and in how many seeds fine-tuned finds more / fewer objects (sign test).

    Averaging over the seeds first keeps a deterministic reference (training-free) fair: an
    object fine-tuning finds with 9 seeds of 10 counts 0.9, not as lost."""
    found, objects = [], []  # per (block, frame): the seeds' mean difference summed over its objects
    for s in scens:
        diff = sum(r[s["name"]]["fine-tuned"].float() - r[s["name"]][other].float() for r in per_seed) / len(per_seed)
        for part in torch.split(diff, [len(frames.gts[i]) for i in s["test"]]):
            found.append(float(part.sum()))
            objects.append(len(part))
    d, n = torch.tensor(found, dtype=torch.float64), torch.tensor(objects, dtype=torch.float64)
    pick = torch.randint(len(d), (draws, len(d)), generator=torch.Generator().manual_seed(0))
    boot = 100 * d[pick].sum(1) / n[pick].sum(1).clamp(min=1)
    per = [sum(int(r[s["name"]]["fine-tuned"].sum()) - int(r[s["name"]][other].sum()) for s in scens)
           for r in per_seed]
    more, fewer = sum(x > 0 for x in per), sum(x < 0 for x in per)
    return {"points": 100 * float(d.sum() / n.sum()), "low": float(boot.quantile(0.025)),
            "high": float(boot.quantile(0.975)), "seeds_more": more, "seeds_fewer": fewer,
            "p_seeds": sign_test(more, fewer)}


def plot(record: dict, path: Path) -> bool:
    """Draw ``record`` (:func:`main`'s) to ``path``: per direction, each adapt block's mean
    recall of the four conditions (bars), and fine-tuning minus each other condition over
    the seeds with its 95 % interval. False (and a line) without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        print("adapt.png skipped: matplotlib is not installed (pip install 'reeb-torch[extras]')", flush=True)
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directions = list(record["paired"])
    colours = {"training-free": "#9e9e9e", "base": "#64b5f6", "scratch": "#ffb74d", "fine-tuned": "#2e7d32"}
    fig, axes = plt.subplots(2, len(directions), figsize=(5.2 * len(directions), 7.2),
                             gridspec_kw={"height_ratios": [3, 2]}, squeeze=False)
    seeds = len(record["seeds"])
    for col, direction in enumerate(directions):
        names = [n for n in record["scenarios"] if n.startswith(direction + ",")]
        ax = axes[0][col]
        width = 0.8 / len(CONDITIONS)
        for j, c in enumerate(CONDITIONS):
            ax.bar([i + (j - 1.5) * width for i in range(len(names))],
                   [record["scenarios"][n]["mean_recall"][c] for n in names], width, label=c, color=colours[c])
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels([n.split(", ", 1)[1] + f"\n({record['scenarios'][n]['objects']} obj.)" for n in names],
                           fontsize=8)
        ax.set_ylim(0, 100)
        ax.set_ylabel("recall @2000, IoU 0.7 (%)")
        ax.set_title(f"{direction}: adapt on the target's first / last k frames", fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
        ax = axes[1][col]
        others = ["training-free", "base", "scratch"]
        rows = [record["paired"][direction][o] for o in others]
        ax.barh(range(len(others)), [r["points"] for r in rows], color=[colours[o] for o in others],
                xerr=[[r["points"] - r["low"] for r in rows], [r["high"] - r["points"] for r in rows]], capsize=4)
        ax.axvline(0, color="black", lw=0.8)
        ax.set_yticks(range(len(others)))
        ax.set_yticklabels([f"vs {o}\n({r['seeds_more']} / {r['seeds_fewer']} seeds)" for o, r in zip(others, rows)],
                           fontsize=8)
        ax.set_xlabel("fine-tuned minus the other (points, 95 % interval)", fontsize=9)
        ax.grid(True, axis="x", alpha=0.3)
    fig.suptitle("A few labelled frames of another drive: reeb fit --init against the alternatives "
                 f"(mean of {seeds} fit seeds)", fontsize=10)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(CONDITIONS), fontsize=8, bbox_to_anchor=(0.5, 0.955))
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", type=Path, metavar="ADAPT_JSON",
                    help="only redraw adapt.png beside this saved adapt.json")
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs(),
                    help="two or more labelled folders (default: the dev folders)")
    ap.add_argument("--k", type=int, nargs="+", default=[5, 10], help="frames to adapt with")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--gap", type=int, default=2, help="frames of a drive kept out beside the adapt block")
    ap.add_argument("--out", type=Path, default=Path("runs/adapt"))
    args = ap.parse_args(argv)
    if args.plot is not None:
        import json

        record = json.loads(args.plot.read_text())
        plot(record, args.plot.with_name("adapt.png"))
        return record
    if len(args.data) < 2:
        ap.error("give two folders or more (--data): a source and a target")
    t0 = time.monotonic()
    frames = F.load_fit_frames([str(d) for d in args.data])
    cache = FrameCache(frames)
    cfg = ReebConfig()
    scens = scenarios(frames, args.k, args.gap)
    text = [f"# rerun: {rerun_line('benchmarks/adapt.py', argv if argv is not None else sys.argv[1:])}",
            "recall at 2000 proposals, IoU 0.7, on the target frames away from the adapt block (%)"]
    per_seed = []
    with tempfile.TemporaryDirectory(prefix="reeb-adapt-") as tmp:
        for seed in args.seeds:
            res = run_seed(cache, cfg, scens, seed, Path(tmp))
            per_seed.append(res)
            for s in scens:
                h = res[s["name"]]
                text.append(f"seed {seed} {s['name']} ({len(s['test'])} frames, {len(h['base'])} objects): "
                            + ", ".join(f"{c} {100 * float(h[c].float().mean()):.1f}" for c in CONDITIONS))
            print("\n".join(text[-len(scens):]), flush=True)
    record: dict = {"seeds": args.seeds, "k": args.k, "environment": environment(), "scenarios": {}, "paired": {}}
    text.append(f"over fit seeds {', '.join(map(str, args.seeds))}: mean recall (%); of the objects each model "
                "finds, the share whose best proposal's class hint is right")
    for s in scens:
        means = {c: 100 * sum(float(r[s["name"]][c].float().mean()) for r in per_seed) / len(per_seed)
                 for c in CONDITIONS}
        record["scenarios"][s["name"]] = {"frames": len(s["test"]), "objects": int(len(per_seed[0][s["name"]]["base"])),
                                          "adapt": [frames.ids[i] for i in s["adapt"]], "mean_recall": means}
        hinted = {c: [sum(r[s["name"]]["hints"][c][j] for r in per_seed) for j in (0, 1)] for c in CONDITIONS[1:]}
        record["scenarios"][s["name"]]["hints_right"] = {c: 100 * a / max(1, b) for c, (a, b) in hinted.items()}
        text.append(f"  {s['name']:<34} " + "  ".join(f"{c} {v:5.1f}" for c, v in means.items())
                    + "  | hints right: "
                    + ", ".join(f"{c} {100 * a / max(1, b):.0f} %" for c, (a, b) in hinted.items()))
    text.append("fine-tuned against each: the difference in recall averaged over the seeds (points), 95 % "
                "bootstrap interval over (block, frame); seeds where fine-tuned finds more / fewer (sign test)")
    for direction in dict.fromkeys(s["direction"] for s in scens):
        mine = [s for s in scens if s["direction"] == direction]
        record["paired"][direction] = {}
        parts = []
        for other in ("training-free", "base", "scratch"):
            row = paired_difference(frames, per_seed, mine, other)
            record["paired"][direction][other] = row
            parts.append(f"against {other} {row['points']:+.1f} ({row['low']:+.1f} to {row['high']:+.1f}), "
                         f"seeds {row['seeds_more']} / {row['seeds_fewer']}, p {row['p_seeds']:.2g}")
        text.append(f"  {direction}: " + "; ".join(parts))
    text.append(f"({time.monotonic() - t0:.0f} s)")
    print("\n".join(text[-(2 + len(scens) + len(record['paired'])):]))
    write_outputs(args.out, "adapt", text, record)
    plot(record, args.out / "adapt.png")
    return record


if __name__ == "__main__":
    main()
