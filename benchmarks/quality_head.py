"""Add a localisation-quality head to an existing ranker's weights, fitted on labelled frames.

The head (:func:`reeb_torch.ranker.training.fit_quality`, used with ``ReebConfig.rank_quality``)
is fitted after the ranking and leaves it as it is, so the file it writes ranks exactly as
the model it started from when ``rank_quality`` is 0: a paired check of the head alone on
other frames (``ranker=OUT;rank_quality=4``). Its rows are the candidates at IoU >= 0.5 with
an object of every frame of ``--data``, as ``reeb fit`` would draw them with
``FitOptions.quality_hidden``; the weights' provenance and config are the start model's, with
the head's command under ``quality_head``.

    python benchmarks/quality_head.py --ranker kitti --out docs/results/ranker/kitti_quality.safetensors
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_dev_dirs, rerun_line  # noqa: E402

from reeb_torch import ReebConfig  # noqa: E402
from reeb_torch.ranker import frames as F  # noqa: E402
from reeb_torch.ranker import fit as RF  # noqa: E402
from reeb_torch.ranker import training as T  # noqa: E402
from reeb_torch.tuning import FrameCache  # noqa: E402
from reeb_torch.ranker import load_ranker, save_ranker  # noqa: E402


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs())
    ap.add_argument("--ranker", default="kitti", help="the weights to start from (a shipped name or a file)")
    ap.add_argument("--hidden", default="32", help="the head's hidden widths, comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None, help="the first N frames of each folder (a smoke run)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    print("# rerun:", rerun_line("benchmarks/quality_head.py", argv if argv is not None else sys.argv[1:]))
    start = load_ranker(args.ranker)
    model = copy.deepcopy(start)
    model.meta = copy.deepcopy(start.meta)
    opts = RF.FitOptions(seed=args.seed, quality_hidden=tuple(int(w) for w in args.hidden.split(",")))
    frames = F.load_fit_frames([str(d) for d in args.data], limit=args.limit)
    cache = FrameCache(frames)
    samples = F.frame_samples(cache, ReebConfig(), opts)
    names = list(cache.candidates(ReebConfig().unranked(), 0).feature_names)
    cols = [names.index(n) for n in model.feature_names]
    x = torch.cat([s.features for s in samples]).float()[:, cols]
    rows = T.quality_rows(torch.cat([s.iou for s in samples]), torch.cat([s.object_weight for s in samples]), x,
                          torch.cat([s.label for s in samples]), opts.quality_iou, opts.balance)
    if rows is None:
        ap.error("no candidate at IoU >= 0.5 with an object: nothing to fit the head on")
    schedule = RF.FitOptions(epochs=opts.quality_epochs, batch=opts.quality_batch)
    T.fit_quality(model.requires_grad_(False), *rows, schedule, opts.seed, opts.quality_hidden)
    model.eval().requires_grad_(False)
    for name, tensor in start.state_dict().items():  # the ranking as it was, bit for bit
        assert torch.equal(tensor, model.state_dict()[name]), name
    provenance = dict(model.meta.get("provenance", {}))
    provenance["quality_head"] = {"command": rerun_line("benchmarks/quality_head.py",
                                                        argv if argv is not None else sys.argv[1:]),
                                  "hidden": list(opts.quality_hidden or ()), "seed": opts.seed,
                                  "frames": len(frames)}
    path = save_ranker(model, args.out, provenance, model.meta.get("config"))
    print(f"{len(frames)} frames, {len(rows[0])} rows of objects; wrote {path} (the ranking of {args.ranker!r} "
          f"and a quality head {opts.quality_hidden})")
    return path


if __name__ == "__main__":
    main()
