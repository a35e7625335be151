"""Recall at 2000 proposals / IoU 0.7 of camera geometries against the default, per folder:
the hand-set default, P2's horizon (ReebConfig.with_kitti_calib), and `reeb calibrate`'s fit.

    python benchmarks/camera_check.py --data ../shared/data/kitti ../shared/data/kitti_tracking \\
        --set kitti:horizon=0.4714,camera_height_m=1.564 ...

Each ``--set NAME:field=value,...`` is scored on every folder (the front end is computed once
per frame, reeb_torch.tuning.FrameCache); a name may be given per folder as NAME@FOLDER.
"""

from __future__ import annotations

import argparse
import json

from reeb_torch import ReebConfig
from reeb_torch import tuning as T
from reeb_torch.metrics.recall import compare_recall


def _parse(text: str) -> tuple[str, dict]:
    name, _, rest = text.partition(":")
    changes = {}
    for pair in filter(None, rest.split(",")):
        k, _, v = pair.partition("=")
        changes[k] = json.loads(v)
    return name, changes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME[@FOLDER]:F=V,...")
    ap.add_argument("-k", type=int, default=2000)
    ap.add_argument("--iou", type=float, default=0.7)
    args = ap.parse_args()
    for root in args.data:
        frames = T.load_frames([root])
        folder = frames.folders[0]
        cache = T.FrameCache(frames)
        base, hb = T.score_config(cache, ReebConfig(), k=args.k, iou=args.iou)
        print(f"== {folder}: default {base}")
        for text in args.sets:
            name, changes = _parse(text)
            if "@" in name:
                name, _, only = name.partition("@")
                if only != folder:
                    continue
            est, hm = T.score_config(cache, ReebConfig().replace(**changes), k=args.k, iou=args.iou)
            print(f"   {name:<24} {changes}: {est}; against the default {compare_recall(hb, hm)}")


if __name__ == "__main__":
    main()
