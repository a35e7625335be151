"""Throughput of ``reeb propose`` on a folder, next to the algorithm on in-memory tensors.

Rows (milliseconds per image, lower is better):

- *decode only*: :func:`reeb_torch.read_image` on every file, one process;
- *algorithm in memory*: ``ProposalGenerator`` on the decoded tensors, grouped by size in
  batches of ``--batch-size`` (after one untimed warm-up call) — the speed to approach;
- *reeb propose, W workers*: the command on the folder, writing JSON Lines, with ``W``
  DataLoader decoding processes (0 = decode inline). "in run" is the command's own
  end-to-end figure (first image decoded to last row written, warm-up included, start-up
  excluded); "algorithm" the time inside the generator; "whole command" adds the Python
  and torch start-up, spread over the images. The "warm" row leaves out the first batch,
  whose first call pays one-off costs that the in-memory figure also leaves out.

With decoding overlapped (W ≥ 1), "in run" should sit close to "algorithm in memory"; the
gap with W = 0 is the decoding that the workers hide.

Rerun: ``python benchmarks/propose_throughput.py [--data DIR] [--limit N] [--workers 0 2]``
(default: the 60 frames in ``../shared/data/kitti/images``). Writes ``propose_throughput.json``
into ``--out`` (default ``runs/propose_throughput``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

try:  # imported as benchmarks.propose_throughput
    from ._common import REPO_ROOT, default_kitti_dir, environment, rerun_line
except ImportError:  # run as a script, or loaded from its file
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import REPO_ROOT, default_kitti_dir, environment, rerun_line  # type: ignore[no-redef]


def _images_dir(data: Path) -> Path:
    return data / "images" if (data / "images").is_dir() else data


def in_memory(paths: Sequence[Path], preset: str, top_k: int, batch_size: int) -> dict[str, float]:
    """Decode every image, then time the generator alone on the tensors."""
    import torch

    import reeb_torch
    from reeb_torch.runs.decoding import Decoded, size_batches

    t0 = time.perf_counter()
    images = [reeb_torch.read_image(p) for p in paths]
    decode_s = time.perf_counter() - t0
    gen = reeb_torch.ProposalGenerator(reeb_torch.get_preset(preset), top_k=top_k).eval()
    gen(images[0][None])  # warm-up (first-call allocations)
    batches = list(size_batches((Decoded(i, str(p), image=im) for i, (p, im) in
                                 enumerate(zip(paths, images))), batch_size))
    n_boxes = 0
    t0 = time.perf_counter()
    for b in batches:
        out = gen(torch.stack([it.image for it in b]))
        n_boxes += sum(len(o["boxes"]) for o in out)
    algo_s = time.perf_counter() - t0
    return {"decode_ms": 1000 * decode_s / len(paths), "algorithm_ms": 1000 * algo_s / len(paths),
            "proposals_per_image": n_boxes / len(paths)}


def cli_run(folder: Path, limit: int | None, workers: int, preset: str, top_k: int,
            batch_size: int) -> dict[str, Any]:
    """Run ``reeb propose`` in a subprocess; its summary JSON plus the whole-command time."""
    with tempfile.TemporaryDirectory() as tmp:
        src = folder
        if limit is not None:  # a folder holding only the first `limit` images (symlinks)
            src = Path(tmp) / "images"
            src.mkdir()
            for p in _list(folder)[:limit]:
                (src / p.name).symlink_to(p.resolve())
        summary = Path(tmp) / "summary.json"
        cmd = [sys.executable, "-m", "reeb_torch.runs.cli", "propose", str(src), "--out",
               str(Path(tmp) / "out.jsonl"), "--preset", preset, "--top-k", str(top_k),
               "--batch-size", str(batch_size), "--workers", str(workers), "--device", "cpu",
               "--summary-json", str(summary), "--quiet"]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO_ROOT)
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"reeb propose failed (exit {r.returncode}):\n{r.stderr}")
        s = json.loads(summary.read_text())
    s["whole_command_ms"] = 1000 * wall / s["processed"]
    return s


def _list(folder: Path) -> list[Path]:
    from reeb_torch.runs.inputs import find_images

    return find_images([folder])[0]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=default_kitti_dir(),
                   help="KITTI folder (with images/) or a folder of images; default: %(default)s")
    p.add_argument("--limit", type=int, default=None, help="use only the first N images")
    p.add_argument("--preset", default="default")
    p.add_argument("--top-k", type=int, default=2000)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    p.add_argument("--out", type=Path, default=Path("runs/propose_throughput"))
    args = p.parse_args(argv)

    folder = _images_dir(args.data)
    if not folder.is_dir():
        raise SystemExit(f"{folder}: no such folder (give --data)")
    paths = _list(folder)[: args.limit] if args.limit else _list(folder)
    n = len(paths)
    print(f"reeb propose throughput: {n} images from {folder}, preset {args.preset}, "
          f"top-k {args.top_k}, batch {args.batch_size}, cpu", flush=True)

    mem = in_memory(paths, args.preset, args.top_k, args.batch_size)
    runs = {w: cli_run(folder, args.limit, w, args.preset, args.top_k, args.batch_size)
            for w in args.workers}

    rows = [("decode only (read_image, 1 process)", f"{mem['decode_ms']:8.1f}", "", ""),
            ("algorithm in memory (tensors, no I/O)", f"{mem['algorithm_ms']:8.1f}", "", "")]
    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:8.1f}"

    for w, s in runs.items():
        name = f"reeb propose, {w} decoding worker{'s' if w != 1 else ''}"
        rows.append((name, ms(s["ms_per_image"]), ms(s["algorithm_ms_per_image"]),
                     ms(s["whole_command_ms"])))
        rows.append(("  same, after the first batch (warm)", ms(s["steady_ms_per_image"]),
                     ms(s["steady_algorithm_ms_per_image"]), ""))
    head = ("", "in run", "algorithm", "whole command")
    width = max(len(r[0]) for r in rows)
    lines = [f"{head[0]:<{width}}  {head[1]:>8}  {head[2]:>9}  {head[3]:>13}   (ms/img)"]
    lines += [f"{a:<{width}}  {b:>8}  {c:>9}  {d:>13}" for a, b, c, d in rows]
    argv_list = list(argv) if argv is not None else sys.argv[1:]
    lines.append(f"rerun: {rerun_line('benchmarks/propose_throughput.py', argv_list)}")
    print("\n".join(lines))

    record = {"images": n, "folder": str(folder), "settings": vars(args) | {"data": str(args.data),
              "out": str(args.out)}, "in_memory": mem, "reeb_propose": {str(k): v for k, v in runs.items()},
              "table": lines, "environment": environment()}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "propose_throughput.json").write_text(json.dumps(record, indent=2) + "\n")
    return record


if __name__ == "__main__":
    main()
