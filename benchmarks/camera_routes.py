"""What each route of ``reeb calibrate`` costs in recall on a camera: calibrate on the frames of
one folder, score on another folder of the same camera.

The routes, each run as the command line runs it on ``--calibrate-on``: nothing set (KITTI's
defaults), ``reeb calibrate DIR`` (labelled boxes), ``reeb calibrate --calib DIR/calib/FILE.txt DIR``
(intrinsics: the file whose ``P2`` has the median ``cy``; KITTI's frames come from several
recording days), ``reeb calibrate DIR --no-labels`` (the images alone). Each camera.json is then scored on ``--score-on``: recall at 2000 proposals / IoU 0.7
with its 95 % frame-bootstrap interval, paired with the labelled route on the same objects
(sign test), as ``reeb eval SCORE_ON --config camera.json`` computes it (the same generator and
recall code; the command is printed beside each row). ``--ranker`` scores with other ranking
weights too (``--set ranker=...`` over each file), e.g. a model that never saw the scored drives.

    # the README's camera: KITTI's frames zoomed 1.33x, horizon at 0.41 (benchmarks/horizon_methods.py makes it)
    python benchmarks/camera_routes.py --calibrate-on runs/horizon/zoom1.33-h0.41/kitti \\
        --score-on runs/horizon/zoom1.33-h0.41/kitti_tracking \\
        --ranker docs/results/ranker/kitti_only_orientation.safetensors --out docs/results/horizon/routes_kitti_to_tracking
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line, write_outputs  # noqa: E402

from reeb_torch.metrics.recall import compare_recall, object_hits, recall_interval  # noqa: E402
from reeb_torch.eval.methods import CONFIGURED, METHODS, Table3Options  # noqa: E402
from reeb_torch.eval.table3 import load_frames, run_method  # noqa: E402
from reeb_torch.config_text import config_from  # noqa: E402

ROUTES = ("nothing set", "labels", "intrinsics", "images")


def median_calib(folder: Path) -> Path:
    """The calibration file of ``folder`` whose ``P2`` row ``cy`` is the median of its files'
    (KITTI's frames come from several recording days, each calibrated on its own)."""
    from reeb_torch.camera import Camera

    files = sorted((folder / "calib").glob("*.txt"))
    return sorted(files, key=lambda f: Camera.from_kitti_calib(f).cy)[len(files) // 2]


def calibrate(route: str, folder: Path, out: Path) -> tuple[Path | None, str]:
    """Run ``reeb calibrate`` by ``route`` on ``folder`` into ``out/<route>.json``: the file
    (None for nothing set) and what the command printed."""
    if route == "nothing set":
        return None, ""
    path = out / f"{route}.json"
    args = {"labels": [str(folder)], "images": [str(folder), "--no-labels"],
            "intrinsics": ["--calib", str(median_calib(folder)), str(folder)]}[route]
    r = subprocess.run([sys.executable, "-m", "reeb_torch.runs.cli", "calibrate", *args, "-o", str(path)],
                       capture_output=True, text=True, check=True)
    return path, r.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calibrate-on", type=Path, required=True, help="folder of the camera to calibrate on")
    ap.add_argument("--score-on", type=Path, required=True, help="another folder of the same camera, scored")
    ap.add_argument("--ranker", action="append", default=[], help="also score with these ranking weights")
    ap.add_argument("--out", type=Path, default=Path("docs/results/horizon/routes"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    files, printed = {}, {}
    for route in ROUTES:
        files[route], printed[route] = calibrate(route, args.calibrate_on, args.out)
    frames = load_frames(Table3Options(data=[args.score_on]))
    text = [rerun_line("benchmarks/camera_routes.py", sys.argv[1:]), "",
            f"calibrated on {args.calibrate_on}; scored on {args.score_on} ({len(frames.images)} frames, "
            f"{frames.n_obj} objects); recall at 2000 proposals, IoU 0.7, 95 % frame-bootstrap interval, "
            "paired with the labelled route on the same objects", ""]
    rows = []
    for ranker in ["kitti", *args.ranker]:
        text += [f"ranking: {ranker}", "", "| route | horizon | camera height | recall (95 % interval) | "
                 "against the labelled route | command |", "|---|---|---|---|---|---|"]
        hits, made = {}, {}
        for route in ROUTES:
            sets = () if ranker == "kitti" else (f"ranker={ranker}",)
            cfg = config_from("default", str(files[route]) if files[route] else None, sets, None)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the ranker's "fitted with other settings" is the point here
                boxes, _ = run_method(METHODS[CONFIGURED], frames.images, 2000, 0, config=cfg)
            hits[route] = object_hits(boxes, frames.gts, 2000, 0.7)
            command = " ".join(["reeb eval", str(args.score_on)] + (["--config", str(files[route])] if files[route]
                                                                     else []) + [f"--set {s}" for s in sets])
            made[route] = (cfg, command)
        for route in ROUTES:
            cfg, command = made[route]
            ci = recall_interval(hits[route])
            row = {"ranker": ranker, "route": route, "horizon": cfg.horizon, "camera_height_m": cfg.camera_height_m,
                   "recall": ci.recall, "low": ci.low, "high": ci.high, "command": command}
            versus = ""
            if route != "labels":
                c = compare_recall(hits["labels"], hits[route])
                versus = f"+{c.gained} / −{c.lost}, p {c.p_value:.2g}"
                row.update(gained=c.gained, lost=c.lost, p_value=c.p_value)
            rows.append(row)
            text.append(f"| {route} | {cfg.horizon:.4f} | {cfg.camera_height_m:.3f} m | {100 * ci.recall:.1f} % "
                        f"({100 * ci.low:.1f}–{100 * ci.high:.1f}) | {versus} | `{command}` |")
        text.append("")
    text += ["what each route printed:", ""] + [f"{r}:\n{printed[r]}" for r in ROUTES if printed[r]]
    print("\n".join(text))
    write_outputs(args.out, "routes", text, {"rows": rows, "files": {r: str(f) for r, f in files.items() if f},
                                            "environment": environment()})
    (args.out / "routes_printed.json").write_text(json.dumps(printed, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
