"""Scale-out: ``reeb propose`` single process against ``--engine ray`` with 1 and 2 actors.

Rows (milliseconds per image on the KITTI frames, lower is better), each a fresh
``reeb propose`` subprocess writing Parquet:

- *single process*: ``reeb propose --engine local`` (torch's default threads, ``-j 2``
  DataLoader decoding workers), and the same with ``OMP_NUM_THREADS=1`` (one torch
  thread, as a Ray actor of one CPU runs: on a busy machine two OpenMP threads that wait
  for each other can be slower than one);
- *ray, N actors*: ``reeb propose --engine ray --actors N`` on a local Ray instance sized
  to the machine; each actor reserves the default :func:`reeb_torch.runs.distributed.actor_cpus`
  (one CPU is left to Ray Data's read/write tasks) and runs that many torch threads.

Columns: "in run" is the command's own end-to-end figure (first image to last row
written; for Ray this includes starting the actors, importing torch in them and building
one generator each, but not ``ray.init``); "Ray start-up" is ``ray.init`` (starting the
local head: GCS, raylet, object store), a one-off cost per command that a long-lived
cluster (``--address``) pays once; "whole command" adds the Python/torch start-up and
Ray's start-up, spread over the images.

Per-image work is independent, so throughput should grow with actors until the CPUs (or
reading, or storage) run out; on a 2-CPU machine shared with other work, 2 actors of half
a CPU each cannot beat one process using both cores.

Rerun: ``python benchmarks/scale_out.py [--data DIR] [--limit N] [--actors 1 2]``
(default: the first 20 frames of ``../shared/data/kitti/images``). Writes
``scale_out.json`` and ``scale_out.txt`` into ``--out`` (default ``docs/results/scale_out``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

try:  # imported as benchmarks.scale_out
    from ._common import REPO_ROOT, default_kitti_dir, environment, rerun_line
except ImportError:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import REPO_ROOT, default_kitti_dir, environment, rerun_line  # type: ignore[no-redef]


def run(images: Sequence[Path], engine: str, actors: int, batch_size: int,
        threads: int | None = None) -> dict[str, Any]:
    """One ``reeb propose`` subprocess on ``images``; its summary plus whole-command time."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "images"
        src.mkdir()
        for p in images:  # a folder holding only these frames (symlinks)
            (src / p.name).symlink_to(p.resolve())
        summary = Path(tmp) / "summary.json"
        out = Path(tmp) / ("out.parquet" if engine == "local" else "out_ray.parquet")
        cmd = [sys.executable, "-m", "reeb_torch.runs.cli", "propose", str(src), "--out", str(out),
               "--batch-size", str(batch_size), "--device", "cpu", "--summary-json",
               str(summary), "--quiet", "--engine", engine]
        if engine == "ray":
            cmd += ["--actors", str(actors)]
        else:
            cmd += ["--workers", "2"]
        env = dict(os.environ)
        if threads is not None:  # torch's (OpenMP's) threads in the single process
            env["OMP_NUM_THREADS"] = str(threads)
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO_ROOT, env=env)
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"reeb propose failed (exit {r.returncode}):\n{r.stderr[-4000:]}")
        s = json.loads(summary.read_text())
    s["whole_command_s"] = wall
    s["whole_command_ms"] = 1000 * wall / s["processed"]
    return s


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--limit", type=int, default=20, help="first N frames (default 20)")
    ap.add_argument("--actors", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "docs" / "results" / "scale_out")
    args = ap.parse_args(argv)
    argv_list = list(argv) if argv is not None else sys.argv[1:]

    from reeb_torch.runs.inputs import find_images

    folder = args.data / "images" if (args.data / "images").is_dir() else args.data
    images = find_images([folder])[0][: args.limit]
    load_before = os.getloadavg()
    runs = [("single process (reeb propose)", run(images, "local", 0, args.batch_size)),
            ("single process, OMP_NUM_THREADS=1", run(images, "local", 0, args.batch_size, 1))]
    for n in args.actors:
        runs.append((f"--engine ray, {n} actor{'s' if n != 1 else ''}",
                     run(images, "ray", n, args.batch_size)))

    def f(v: float | None, fmt: str = "{:.0f}") -> str:
        return "-" if v is None else fmt.format(v)

    load_after = os.getloadavg()
    lines = [f"reeb propose on {len(images)} KITTI frames ({folder}), batch {args.batch_size}, CPU; "
             f"{os.cpu_count()} CPUs, load average {load_before[0]:.1f} before, {load_after[0]:.1f} after",
             "",
             f"{'run':34s} {'in run ms/img':>14s} {'Ray start-up s':>15s} {'whole command ms/img':>21s}"
             f" {'CPUs/actor':>11s}"]
    for name, s in runs:
        lines.append(f"{name:34s} {f(s['ms_per_image']):>14s} {f(s.get('ray_startup_s'), '{:.1f}'):>15s}"
                     f" {f(s['whole_command_ms']):>21s} {f(s.get('cpus_per_actor'), '{:g}'):>11s}")
    lines += ["", f"rerun: {rerun_line('benchmarks/scale_out.py', argv_list)}"]
    text = "\n".join(lines)
    print(text)
    record = {"images": [str(p) for p in images], "load_average": [load_before, load_after], "runs": [dict(name=n, **s) for n, s in runs],
              "table": lines, "environment": environment()}
    for _, s in runs:
        s.pop("failures", None)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scale_out.json").write_text(json.dumps(record, indent=2) + "\n")
    (args.out / "scale_out.txt").write_text(text + "\n")
    return record


if __name__ == "__main__":
    main()
