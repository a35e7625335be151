"""What more labelled frames buy the learned ranking: its whole-drives estimate when each
fold's model is fitted on a quarter, a half and all of that fold's training frames.

The folds are ``reeb fit --folds 10 --whole-drives``'s (every frame of a held-out block's
drives out of its training frames); within each fold the model is fitted on every 4th, every
2nd or every training frame (in frame order, so each share spans the same drives), and
scored on the held-out block, which is the same for every share. Recall @2000 / IoU 0.7 with
its frame-bootstrap interval, per class, and each share paired with all frames (the sign
test on the same objects), over ``--seeds`` fit seeds (an object counts as found with more /
fewer seeds, as in ``cv_paired.py``).

    python benchmarks/learning_curve.py --seeds 0 1 2 --out docs/results/ranker/learning_curve
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, environment, rerun_line, write_outputs  # noqa: E402

from reeb_torch import ReebConfig  # noqa: E402
from reeb_torch.ranker import frames as F  # noqa: E402
from reeb_torch.metrics.recall import sign_test  # noqa: E402
from reeb_torch.tuning import FrameCache, bootstrap_interval, fold_blocks  # noqa: E402
from reeb_torch.ranker import fit as RF  # noqa: E402
from reeb_torch.ranker import save_ranker  # noqa: E402

SHARES = {"a quarter": 4, "a half": 2, "all": 1}
"""Each share of a fold's training frames: every n-th of them."""


def held_out_hits(cache: FrameCache, samples, blocks: list[list[int]], every: int, seed: int, k: int,
                  iou: float, scratch: Path) -> tuple[list[torch.Tensor], list[int]]:
    """Per frame (in frame order), the objects found by the model fitted on every ``every``-th
    training frame of its fold; and the frames each fold's model was fitted on."""
    frames = cache.frames
    similar = F.similar_frames(frames.images)
    names = cache.candidates(ReebConfig().unranked(), 0).feature_names
    opts = dataclasses.replace(RF.FitOptions(), seed=seed)
    hits: list = [None] * len(frames)
    trained = []
    for f, block in enumerate(blocks):
        train = F.training_frames(blocks, f, frames.ids, frames.folders, similar, gap=len(frames))[::every]
        model = RF.fit_ranker([samples[i] for i in train], names, opts, frames.classes)
        trained.append(len(train))
        cfg = ReebConfig().replace(ranker=str(save_ranker(model, scratch / f"s{seed}-e{every}-f{f}.safetensors")))
        for i, h in zip(block, cache.hits(cfg, block, k, iou)):
            hits[i] = h
    return hits, trained


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs(), metavar="DIR")
    ap.add_argument("--folds", type=int, default=10)
    ap.add_argument("--limit", type=int, help="the first N frames of each folder (a quick check)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("-k", type=int, default=2000)
    ap.add_argument("--iou", type=float, default=0.7)
    ap.add_argument("--out", type=Path, default=Path("docs/results/ranker/learning_curve"))
    args = ap.parse_args(argv)
    frames = F.load_fit_frames(args.data, limit=args.limit)
    cache = FrameCache(frames)
    samples = F.frame_samples(cache, ReebConfig(), RF.FitOptions())  # the rows do not depend on the fit seed
    blocks = fold_blocks(len(frames), args.folds)
    labels = frames.labels
    found: dict[str, list[list[torch.Tensor]]] = {s: [] for s in SHARES}
    trained: dict[str, list[int]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for share, every in SHARES.items():
                hits, trained[share] = held_out_hits(cache, samples, blocks, every, seed, args.k, args.iou, Path(tmp))
                found[share].append(hits)
                print(f"seed {seed}, {share}: {100 * sum(int(h.sum()) for h in hits) / sum(h.numel() for h in hits):.1f} %",
                      flush=True)
    lines = [f"{len(frames)} frames, {sum(len(g) for g in frames.gts)} objects; {args.folds} folds, whole drives "
             f"held out; recall @{args.k} / IoU {args.iou}; fit seeds {' '.join(map(str, args.seeds))}",
             f"{'share of training frames':<26}{'frames fitted':>14}  {'recall % (95 % interval)':<26}"
             f"{'per class':<52}against all"]
    record = {"command": rerun_line("benchmarks/learning_curve.py", sys.argv[1:] if argv is None else argv),
              "environment": environment(), "shares": {}}
    total = {s: [torch.stack([h[i] for h in found[s]]).float().mean(0) for i in range(len(frames))] for s in SHARES}
    for share in SHARES:
        per_seed = [bootstrap_interval(h, labels) for h in found[share]]
        mean = sum(e.recall for e in per_seed) / len(per_seed)
        lo = sum(e.low for e in per_seed) / len(per_seed)
        hi = sum(e.high for e in per_seed) / len(per_seed)
        per_class = {}
        for c, name in enumerate(frames.classes):
            n = sum(int((x == c).sum()) for x in labels)
            if n:
                per_class[name] = 100 * sum(float(t[x == c].sum()) for t, x in zip(total[share], labels)) / n
        gained = sum(int((a > b).sum()) for a, b in zip(total[share], total["all"]))
        lost = sum(int((a < b).sum()) for a, b in zip(total[share], total["all"]))
        p = sign_test(gained, lost) if share != "all" else 1.0
        paired = "" if share == "all" else f"+{gained} / -{lost}, p {p:.2g}"
        shown = ", ".join(f"{n} {v:.1f}" for n, v in per_class.items())
        lines.append(f"{share:<26}{sum(trained[share]) / len(trained[share]):>14.1f}  "
                     f"{100 * mean:5.1f} ({100 * lo:.1f}-{100 * hi:.1f}){'':<8}{shown:<52}{paired}")
        record["shares"][share] = {"every": SHARES[share], "frames_fitted_mean": sum(trained[share]) / len(trained[share]),
                                   "recall": 100 * mean, "interval_95": [100 * lo, 100 * hi], "per_class": per_class,
                                   "per_seed": [100 * e.recall for e in per_seed],
                                   "against_all": {"gained": gained, "lost": lost, "p_value": p}}
    write_outputs(args.out, "learning_curve", lines, record)


if __name__ == "__main__":
    main()
