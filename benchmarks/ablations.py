"""Ablations that settle the paper's ambiguities (NOTES.md) by measured recall.

Each row changes one switch of the package default (``ReebConfig()``), or starts from
the ``paper`` preset, and reports recall of the top 2000 proposals at IoU 0.5 and 0.7
(micro, all objects of the four classes), AR, and ms/img, on the same KITTI frames.

Rerun: ``python benchmarks/ablations.py [--data DIR] [--limit N] [--only NAME ...]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir, environment, rerun_line  # noqa: E402

from reeb_torch import ProposalGenerator, ReebConfig  # noqa: E402
from reeb_torch.data import KittiDataset  # noqa: E402
from reeb_torch.metrics import average_recall, recall_table  # noqa: E402

D = ReebConfig()
P = ReebConfig.paper()

# name -> (config, NOTES item it settles)
VARIANTS: dict[str, tuple[ReebConfig, str]] = {
    "default": (D, "package default"),
    "paper": (P, "printed text"),
    "default, no regions": (D.replace(use_regions=False), "Ours* vs Ours**"),
    "norm=area (γ=0.75)": (D.replace(score_norm="area"), "#1"),
    "kappa=1.25": (D.replace(kappa=1.25), "#1"),
    "kappa=1.75": (D.replace(kappa=1.75), "#1"),
    "grouping=connected, unbounded": (D.replace(grouping="connected", group_cell=None), "#2"),
    "grouping=connected, 4px tiles": (D.replace(grouping="connected", group_cell=4), "#2"),
    "grouping=connected, 16px tiles": (D.replace(grouping="connected", group_cell=16), "#2"),
    "grouping=cell 8": (D.replace(grouping="cell", group_cell=8), "#2"),
    "edge_threshold=0.1": (D.replace(edge_threshold=0.1), "#4"),
    "edge_threshold=0.02": (D.replace(edge_threshold=0.02), "#4"),
    "blur_sigma=0.7": (D.replace(blur_sigma=0.7), "#4"),
    "blur_sigma=1.5": (D.replace(blur_sigma=1.5), "#4"),
    "thin_edges=off": (D.replace(thin_edges=False), "#4"),
    "edge_channels=rgb": (D.replace(edge_channels="rgb"), "#4"),
    "entropy_bins=16": (D.replace(entropy_bins=16), "#9"),
    "road_score=reward": (D.replace(road_score="reward"), "#10"),
    "road_score=reward, OR": (D.replace(road_score="reward", road_combine="or"), "#5, #10"),
    "road_score=penalize": (D.replace(road_score="penalize"), "#10"),
    "location=paper": (D.replace(location_score="paper"), "#11"),
    "location=none": (D.replace(location_score="none"), "#11"),
    "min_edge_score=0.01": (D.replace(min_edge_score=0.01), "#12"),
    "region_assign=contained": (D.replace(region_assign="contained"), "#13"),
    "ground_band=off": (D.replace(ground_band=None), "#13"),
    "local_max=on": (D.replace(local_max=True), "#13"),
    "window_step=0.1": (D.replace(window_step=0.1), "#13"),
    "window_step=0.2": (D.replace(window_step=0.2), "#13"),
    "size_ratio=1.15": (D.replace(size_ratio=1.15), "#13"),
    "scale=1.0": (D.replace(scale=1.0, group_cell=16), "#13"),
    "nms_iou=0.8": (D.replace(nms_iou=0.8), "#14"),
    "candidates_per_region=8000": (D.replace(candidates_per_region=8000), "eq. 9"),
    "region_quota=on": (D.replace(region_quota=True), "eq. 9"),
}


def load(root: Path, limit: int | None):
    ds = KittiDataset(root, limit=limit)
    items = [ds[i] for i in range(len(ds))]
    return [it["image"] for it in items], [it["boxes"] for it in items], [it["labels"] for it in items], ds.classes


def run(cfg: ReebConfig, images, batch: int) -> tuple[list[torch.Tensor], float]:
    gen = ProposalGenerator(cfg)
    gen(images[:1])  # warm-up (window grids are cached per size)
    boxes: list[torch.Tensor] = []
    t0 = time.perf_counter()
    for i in range(0, len(images), batch):
        boxes += [o["boxes"] for o in gen(images[i: i + batch])]
    return boxes, (time.perf_counter() - t0) * 1000 / len(images)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (substring match)")
    ap.add_argument("--out", type=Path, default=Path("runs/ablations"))
    args = ap.parse_args(argv)
    print("# rerun:", rerun_line("benchmarks/ablations.py", argv if argv is not None else sys.argv[1:]))
    images, gts, labels, classes = load(args.data, args.limit)
    print(f"# {len(images)} images from {args.data}, {sum(len(g) for g in gts)} objects, "
          f"torch threads {torch.get_num_threads()}")
    print(f"{'variant':34s} {'NOTES':6s} {'R@.5':>6s} {'R@.7':>6s} {'AR':>6s} {'ms/img':>7s}")
    rows = []
    for name, (cfg, note) in VARIANTS.items():
        if args.only and not any(s in name for s in args.only):
            continue
        boxes, ms = run(cfg, images, args.batch)
        res = recall_table(boxes, gts, labels, classes, ks=(2000,), ious=(0.5, 0.7))
        ar = float(average_recall(boxes, gts, ks=(2000,))[0])
        r5, r7 = res.at(2000, 0.5), res.at(2000, 0.7)
        print(f"{name:34s} {note:6s} {100 * r5:6.1f} {100 * r7:6.1f} {100 * ar:6.1f} {ms:7.1f}", flush=True)
        rows.append(dict(variant=name, notes=note, recall_05=r5, recall_07=r7, ar=ar, ms_per_img=ms))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablations.json").write_text(json.dumps({"rows": rows, "env": environment()}, indent=2))
    return rows


if __name__ == "__main__":
    main()
