"""How many labelled objects REEB's window grid covers at IoU 0.7, by class and height, from the
label geometry alone (no image).

REEB's windows are a grid that depends only on the image size and the settings
(:mod:`reeb_torch.stages.windows`; the regions set budgets, not windows). This builds the grid
a ``--width`` × ``--height`` frame gets (each ``--set`` variant's), and for every labelled
object of ``Car``, ``Pedestrian`` and ``Cyclist`` at least 25 px tall finds the window of
highest IoU: the share with a window at ``--iou`` or more is the grid's coverage, the ceiling
of what scoring, the ranking and NMS can keep. Labels come from KITTI-format folders
(``labels/``, ``label_2/``) and from KITTI tracking label files (``label_02/SSSS.txt``, 17
fields a line; their frames are taken to be ``--width`` × ``--height``).

    python benchmarks/window_coverage.py --folders ../shared/data/kitti ../shared/data/kitti_tracking \\
        --tracking ../shared/data/kitti_tracking_labels/*.txt --variant default="" \\
        --variant step_0.05="window_step=0.05" --out docs/results/window_coverage

Writes ``OUT/coverage.txt`` (the table) and ``OUT/coverage.json`` (per variant, class and
height bucket: objects, covered, the mean best IoU; the window count).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import rerun_line  # noqa: E402

CLASSES = ("Car", "Pedestrian", "Cyclist")
BUCKETS = ((25, 40), (40, 60), (60, 100), (100, 10_000))
"""Box heights in pixels: [lo, hi)."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--folders", nargs="*", type=Path, default=[], help="labelled KITTI-format folders")
    p.add_argument("--tracking", nargs="*", type=Path, default=[], help="KITTI tracking label files (17 fields)")
    p.add_argument("--variant", action="append", default=[], metavar='NAME="FIELD=VALUE ..."',
                   help="settings over the default (reeb propose's --set items); repeatable [default: the default]")
    p.add_argument("--width", type=int, default=1242, help="frame width of the tracking labels, px")
    p.add_argument("--height", type=int, default=375, help="frame height of the tracking labels, px")
    p.add_argument("--iou", type=float, default=0.7, help="IoU a window needs to cover an object")
    p.add_argument("--out", type=Path, help="folder for coverage.txt and coverage.json")
    args = p.parse_args(argv)
    if not args.folders and not args.tracking:
        p.error("give --folders or --tracking")
    return args


def objects(folders: list[Path], tracking: list[Path], size: tuple[int, int]) -> list[dict[str, Any]]:
    """Every object of :data:`CLASSES` at least 25 px tall: ``class``, ``box`` (x1, y1, x2,
    y2), ``size`` (W, H of its frame), ``source``."""
    from PIL import Image

    from reeb_torch.datasets.kitti import KittiDataset, read_kitti_labels

    out = []
    for root in folders:
        ds = KittiDataset(root)
        for path, image_id in zip(ds.image_paths, ds.ids):
            with Image.open(path) as im:
                frame = im.size
            for o in read_kitti_labels(ds.label_dir / f"{image_id}.txt", CLASSES):
                out.append({"class": o.type, "box": tuple(o.box), "size": frame, "source": root.name})
    for f in tracking:
        for line in f.read_text(encoding="utf-8").splitlines():
            v = line.split()
            if len(v) >= 10 and v[2] in CLASSES:
                out.append({"class": v[2], "box": tuple(float(x) for x in v[6:10]), "size": size,
                            "source": f"tracking {f.stem}"})
    return [o for o in out if o["box"][3] - o["box"][1] >= BUCKETS[0][0]]


def windows(sets: list[str], size: tuple[int, int]) -> Any:
    """The window grid a ``size`` (W, H) frame gets with ``sets``, in input pixels (``float32
    [N, 4]``): the generator's own grid of a frame of that size, one region across it."""
    import torch

    from reeb_torch import ProposalGenerator
    from reeb_torch.config_text import config_from

    gen = ProposalGenerator(config_from("default", None, [*sets, "ranker=none"], None))  # the grid: no ranker
    w, h = size
    front = gen.front_end(gen.prepare([torch.zeros(3, h, w, dtype=torch.uint8)]))
    maps = front.maps
    hk, wk = maps.edges.shape[-2:]
    grid = gen.selection.window_grid(maps, torch.tensor([[0, wk]]))
    scale = torch.tensor([maps.fx, maps.fy, maps.fx, maps.fy])
    return grid.boxes / scale


def best_iou(boxes: Any, grid: Any) -> Any:
    """For each of ``boxes`` ``[M, 4]``, the highest IoU over ``grid`` ``[N, 4]``."""
    import torch
    from torchvision.ops import box_iou

    return torch.cat([box_iou(boxes[i:i + 64], grid).amax(1) for i in range(0, len(boxes), 64)]) \
        if len(boxes) else torch.zeros(0)


def coverage(objs: list[dict[str, Any]], sets: list[str], iou: float) -> dict[str, Any]:
    import torch

    record: dict[str, Any] = {"windows": {}, "classes": {}}
    best = torch.zeros(len(objs))
    for size in sorted({o["size"] for o in objs}):
        grid = windows(sets, size)
        record["windows"][f"{size[0]}x{size[1]}"] = len(grid)
        idx = [i for i, o in enumerate(objs) if o["size"] == size]
        best[idx] = best_iou(torch.tensor([objs[i]["box"] for i in idx]), grid)
    for c in CLASSES:
        rows = {}
        for lo, hi in BUCKETS:
            sel = [i for i, o in enumerate(objs) if o["class"] == c and lo <= o["box"][3] - o["box"][1] < hi]
            b = best[sel]
            rows[f"{lo}-{hi}" if hi < 10_000 else f">={lo}"] = {
                "objects": len(sel), "covered": int((b >= iou).sum()),
                "mean_best_iou": round(float(b.mean()), 4) if len(sel) else None}
        record["classes"][c] = rows
    return record


def table(results: dict[str, dict[str, Any]], iou: float) -> str:
    lines = [f"share of objects with a window at IoU >= {iou} (objects), mean best IoU; by box height in px",
             "", "| variant | windows | class | " + " | ".join(
                 (f"{lo}-{hi}" if hi < 10_000 else f">={lo}") for lo, hi in BUCKETS) + " | all >= 25 |",
             "|---|---|---|" + "---|" * (len(BUCKETS) + 1)]
    for name, rec in results.items():
        count = ", ".join(f"{n} ({s})" for s, n in rec["windows"].items())
        for c, rows in rec["classes"].items():
            cells = [f"{100 * r['covered'] / r['objects']:.1f} % ({r['objects']}), {r['mean_best_iou']:.2f}"
                     if r["objects"] else "-" for r in rows.values()]
            n = sum(r["objects"] for r in rows.values())
            k = sum(r["covered"] for r in rows.values())
            cells.append(f"{100 * k / n:.1f} % ({n})" if n else "-")
            lines.append(f"| {name} | {count} | {c} | " + " | ".join(cells) + " |")
            count = ""
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    objs = objects(args.folders, args.tracking, (args.width, args.height))
    variants = [v.partition("=") for v in (args.variant or ['default=""'])]
    results = {name: coverage(objs, shlex.split(sets.strip('"')), args.iou) for name, _, sets in variants}
    text = table(results, args.iou)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        rerun = rerun_line("benchmarks/window_coverage.py", argv if argv is not None else sys.argv[1:])
        (args.out / "coverage.txt").write_text(f"# rerun: {rerun}\n{text}\n", encoding="utf-8")
        (args.out / "coverage.json").write_text(json.dumps({"rerun": rerun, "iou": args.iou,
                                                            "variants": {n: s for n, _, s in variants},
                                                            "results": results}, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
