"""Both fits at a user's scale: ``reeb fit`` and ``reeb detector fit`` on copies of the dev
frames, 1×, 2×, 8× (``--scales``), each copy mirrored and/or brightened so that every image
differs: the peak resident memory of each fit (its process's, ``wait4``'s maximum RSS), the
peak disk of what it keeps (the ranker's row store, the detector's map cache), and the time
of each stage.

    python benchmarks/fit_scale.py --out docs/results/fit_scale
    python benchmarks/fit_scale.py --scales 1 2 --fits ranker --folds 2 --epochs 2   # quicker

Copy ``c`` of a frame is the frame flipped left to right where ``c`` is odd (its boxes
flipped with it), with ``6·⌈c/2⌉`` grey levels added (clipped); its id is the frame's with
``c`` in front (``1000123`` for object frame ``000123``; ``t0000c1_000012`` for a tracking
frame, a drive of its own). The ranker fit runs as the issue's check does
(``--folds 2 --epochs 2``), the detector fit ``--epochs 1``, each in a fresh process with an
empty cache, ``--code DIR`` choosing another checkout to run (the code before, for a pairing).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, default_dev_dirs, environment, rerun_line, write_outputs  # noqa: E402


def copy_id(image_id: str, c: int) -> str:
    """Copy ``c``'s id of frame ``image_id`` (module doc)."""
    if c == 0:
        return image_id
    m = re.match(r"^(.+)_(\d+)$", image_id)
    return f"{m.group(1)}c{c}_{m.group(2)}" if m else f"{c}{image_id}"


def _flip_label(line: str, width: int) -> str:
    f = line.split()
    if len(f) < 8:
        return line
    x1, x2 = float(f[4]), float(f[6])
    f[4], f[6] = f"{width - x2:.2f}", f"{width - x1:.2f}"
    return " ".join(f)


def make_copies(src: Path, dst: Path, scale: int) -> Path:
    """``dst/<src name>``: ``scale`` copies of each labelled frame of the KITTI-format folder
    ``src`` (``images/`` + ``labels/`` + ``calib/``, or KITTI's names), written once."""
    import cv2
    import numpy as np

    out = dst / src.name
    done = out / ".complete"
    if done.exists():
        return out
    images = next(p for p in (src / "images", src / "image_2") if p.is_dir())
    labels = next(p for p in (src / "labels", src / "label_2") if p.is_dir())
    calib = next((p for p in (src / "calib",) if p.is_dir()), None)
    for sub in ("images", "labels", "calib"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for png in sorted(images.glob("*.png")):
        stem = png.stem
        label = labels / f"{stem}.txt"
        if not label.exists():
            continue
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        width = img.shape[1]
        lines = label.read_text().splitlines()
        for c in range(scale):
            new = copy_id(stem, c)
            x = img[:, ::-1] if c % 2 else img
            if c:
                x = np.clip(x.astype(np.int16) + 6 * ((c + 1) // 2), 0, 255).astype(np.uint8)
            cv2.imwrite(str(out / "images" / f"{new}.png"), np.ascontiguousarray(x))
            text = [_flip_label(t, width) if c % 2 else t for t in lines]
            (out / "labels" / f"{new}.txt").write_text("\n".join(text) + "\n")
            if calib is not None and (calib / f"{stem}.txt").exists():
                shutil.copy(calib / f"{stem}.txt", out / "calib" / f"{new}.txt")
    done.touch()
    return out


def _du(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def run(cmd: list[str], watch: Path, env: dict[str, str], cwd: Path) -> dict:
    """Run ``cmd`` in ``cwd``; its peak RSS (GB), wall seconds, the peak bytes under ``watch``
    and its output."""
    peak = [0]
    stop = threading.Event()

    def poll() -> None:
        while not stop.wait(1.0):
            peak[0] = max(peak[0], _du(watch))

    t = threading.Thread(target=poll, daemon=True)
    t.start()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True, cwd=cwd)
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - t0
    stop.set()
    t.join()
    peak[0] = max(peak[0], _du(watch))
    return {"rss_gb": round(usage.ru_maxrss / 1024 ** 2, 3), "wall_s": round(wall, 1),
            "disk_gb": round(peak[0] / 1024 ** 3, 3), "status": os.waitstatus_to_exitcode(status),
            "output": out[-3000:]}


def _stages(output: str) -> dict[str, float]:
    """The stage times a fit printed (``stages: rows 12 s, ...``; the detector's training line)."""
    found: dict[str, float] = {}
    m = re.search(r"^stages: (.+)$", output, re.M)
    if m:
        for part in m.group(1).split(", "):
            name, _, value = part.rpartition(" ")[0].rpartition(" ")
            found[name] = float(value)
    m = re.search(r"(\d+) steps, (\d+) s of head training, (\d+) s in all", output)
    if m:
        found.update(frames=float(m.group(3)) - float(m.group(2)), training=float(m.group(2)))
    return found


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, nargs="+", default=default_dev_dirs(), metavar="DIR")
    ap.add_argument("--scales", type=int, nargs="+", default=[1, 2, 8])
    ap.add_argument("--fits", nargs="+", choices=["ranker", "detector"], default=["ranker", "detector"])
    ap.add_argument("--folds", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=2, help="the ranker's epochs (the detector's: 1)")
    ap.add_argument("--work", type=Path, help="where the copies and outputs go (default: a temporary folder)")
    ap.add_argument("--code", type=Path, default=REPO_ROOT, help="the checkout whose reeb_torch runs")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "docs" / "results" / "fit_scale")
    args = ap.parse_args(argv)
    work = (args.work or Path(tempfile.mkdtemp(prefix="reeb-fit-scale-"))).resolve()
    args.data = [d.resolve() for d in args.data]
    env = {**os.environ, "PYTHONPATH": str(args.code.resolve())}
    cli = [sys.executable, "-m", "reeb_torch.runs.cli"]
    rows = []
    for scale in args.scales:
        data = [make_copies(d, work / f"x{scale}", scale) for d in args.data]
        frames = sum(len(list((d / "images").glob("*.png"))) for d in data)
        for fit in args.fits:
            run_dir = work / f"x{scale}-{fit}"
            shutil.rmtree(run_dir, ignore_errors=True)
            run_dir.mkdir(parents=True)
            if fit == "ranker":
                cmd = [*cli, "fit", *map(str, data), "--folds", str(args.folds), "--epochs", str(args.epochs), "-q",
                       "-o", str(run_dir / "ranker.safetensors")]
            else:
                cmd = [*cli, "detector", "fit", *map(str, data), "--epochs", "1", "-q", "--cache",
                       str(run_dir / "cache"), "-o", str(run_dir / "detector.safetensors")]
            r = run(cmd, run_dir, env, args.code.resolve())  # there, `python -m` imports that checkout's package
            row = {"fit": fit, "scale": scale, "frames": frames, **{k: v for k, v in r.items() if k != "output"},
                   "stages_s": _stages(r["output"])}
            if r["status"] != 0:
                row["error"] = r["output"][-600:]
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"{'fit':<9}{'scale':>6}{'frames':>8}{'peak RSS GB':>13}{'disk GB':>9}{'wall s':>8}  stages (s)"]
    for r in rows:
        stages = ", ".join(f"{k} {v:.0f}" for k, v in r["stages_s"].items())
        lines.append(f"{r['fit']:<9}{r['scale']:>6}{r['frames']:>8}{r['rss_gb']:>13.2f}{r['disk_gb']:>9.2f}"
                     f"{r['wall_s']:>8.0f}  {stages}" + ("  FAILED" if r["status"] else ""))
    for fit in args.fits:
        mine = [r for r in rows if r["fit"] == fit and not r["status"]]
        if len(mine) > 1:
            a, b = mine[0], mine[-1]
            per = (b["rss_gb"] - a["rss_gb"]) / (b["frames"] - a["frames"]) * 1024
            lines.append(f"{fit}: peak RSS {a['rss_gb']:.2f} GB at {a['frames']} frames, {b['rss_gb']:.2f} GB at "
                         f"{b['frames']} ({per:+.2f} MB per frame); time per frame {a['wall_s'] / a['frames']:.2f} "
                         f"s at {a['frames']}, {b['wall_s'] / b['frames']:.2f} s at {b['frames']}")
    record = {"command": rerun_line("benchmarks/fit_scale.py", sys.argv[1:] if argv is None else argv),
              "code": str(args.code), "environment": environment(), "rows": rows}
    write_outputs(args.out, "fit_scale", lines, record)


if __name__ == "__main__":
    main()
