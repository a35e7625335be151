"""Where REEB loses objects: recall after each stage of the pipeline.

For each ground-truth object, the best IoU with (1) every sliding window of the grid,
(2) the windows with a valid score (S above ``min_edge_score``), (3) the candidates the
regions pass on (eq. 9 budgets), (4) the final ``top_k`` after NMS. Recall at IoU 0.5 and
0.7 over all objects (micro), on the frames of a KITTI-format folder.

Rerun: ``python benchmarks/diagnose_recall.py [--data DIR] [--limit N] [--preset NAME]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torchvision.ops import box_iou

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir, rerun_line  # noqa: E402

from reeb_torch import ProposalGenerator, get_preset  # noqa: E402
from reeb_torch.data import KittiDataset  # noqa: E402


def stage_ious(gen: ProposalGenerator, image: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """Best IoU of each object in ``gt`` at each stage, for one uint8 image."""
    captured: dict = {}
    orig_select = gen._select

    def select(scores, grid, share):  # record what the pipeline saw
        chosen = orig_select(scores, grid, share)
        captured.update(scores=scores, grid=grid, chosen=chosen)
        return chosen

    gen._select = select  # type: ignore[method-assign]
    try:
        out = gen([image])[0]
    finally:
        del gen._select
    h, w = image.shape[-2:]
    s = gen.config.scale
    hk, wk = max(1, round(h * s)), max(1, round(w * s))
    boxes = captured["grid"].boxes / torch.tensor([wk / w, hk / h, wk / w, hk / h])
    iou = box_iou(gt, boxes)
    valid = torch.isfinite(captured["scores"][0])[None]
    chosen = captured["chosen"][0][None]
    final = box_iou(gt, out["boxes"]) if len(out["boxes"]) else torch.zeros(len(gt), 1)
    zero = torch.zeros(())
    return {
        "all windows": iou.max(1).values,
        "valid score": torch.where(valid, iou, zero).max(1).values,
        "region candidates": torch.where(chosen, iou, zero).max(1).values,
        "final top-k": final.max(1).values,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--preset", default="default")
    args = ap.parse_args(argv)
    print("# rerun:", rerun_line("benchmarks/diagnose_recall.py", argv if argv is not None else sys.argv[1:]))
    ds = KittiDataset(args.data, limit=args.limit)
    gen = ProposalGenerator(get_preset(args.preset))
    acc: dict[str, list[torch.Tensor]] = {}
    for i in range(len(ds)):
        item = ds[i]
        if len(item["boxes"]) == 0:
            continue
        for k, v in stage_ious(gen, item["image"], item["boxes"]).items():
            acc.setdefault(k, []).append(v)
    n = sum(len(v) for v in acc["all windows"])
    print(f"# {len(ds)} frames, {n} objects, preset {args.preset}")
    print(f"{'stage':20s} {'R@0.5':>7s} {'R@0.7':>7s}")
    for k, v in acc.items():
        b = torch.cat(v)
        print(f"{k:20s} {100 * float((b >= 0.5).float().mean()):7.1f} {100 * float((b >= 0.7).float().mean()):7.1f}")


if __name__ == "__main__":
    main()
