"""Milliseconds per image of ``reeb detect``'s work, per stage, at batch 1 and batch 8.

For each ``--detector`` file (``reeb detector fit``'s) this runs what ``reeb detect`` runs on
the images: ``ReebDetector([images])`` on batches of ``--batch`` images, the images moved to
``--device`` inside the timed call as the command does; the stages are timed with the
command's own hooks (:class:`reeb_torch.runs.detect_run.StageTimes`: REEB's proposals, the
backbone, the heads; on CUDA each stage waits for the GPU) and the rest of the call
(resize and normalisation before the backbone, boxes back to input pixels after the heads)
is ``other``. Decoding (``reeb_torch.io.read_image``, which ``reeb detect``'s worker
processes run beside the detector) is timed apart, in this process. The first batch of
each (detector, batch size) is a warm-up and not counted; then ``--repeats`` passes over
all images, every (detector, batch) once per pass in turn (a slow spell of a shared machine
hits all alike), and the median pass is reported (of an even number, the faster of the
middle two).

Without ``--detector``, ``--min-size N`` builds detectors with untrained heads at those
input sizes: the same computation as trained ones, except the heads' NMS, which sees other
scores.

    python benchmarks/detect_speed.py ../shared/data/kitti/images --limit 8 \\
        --detector det.safetensors --batch 1 8 --out docs/results/detector/speed

Writes ``OUT/speed.txt`` and ``OUT/speed.json`` (per detector ``name`` and batch: ms/img per
stage, ``detector`` their sum, ``serial_end_to_end`` with decoding, ``passes_ms`` every pass; the machine, its load average before and after).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, rerun_line  # noqa: E402

STAGES = ("decode", "proposals", "backbone", "heads", "other", "detector")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("images", nargs="*", type=Path, default=[REPO_ROOT / "examples" / "data"],
                   help="image files or folders (default: the bundled examples/data)")
    p.add_argument("--detector", type=Path, action="append", default=[], metavar="FILE",
                   help="a detector file (repeat for several)")
    p.add_argument("--min-size", type=int, nargs="+", default=[], metavar="N",
                   help="without --detector: untrained detectors at these input sizes")
    p.add_argument("--batch", type=int, nargs="+", default=[1, 8], help="batch sizes (default: 1 8)")
    p.add_argument("--limit", type=int, help="only the first N images")
    p.add_argument("--repeats", type=int, default=2, help="timed passes over the images")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--out", type=Path, help="folder for speed.txt and speed.json")
    args = p.parse_args(argv)
    if not args.detector and not args.min_size:
        p.error("give --detector FILE or --min-size N")
    return args


def image_paths(inputs: list[Path], limit: int | None) -> list[Path]:
    exts = {".png", ".jpg", ".jpeg", ".bmp", ".webp"}
    out: list[Path] = []
    for p in inputs:
        out += sorted(q for q in p.iterdir() if q.suffix.lower() in exts) if p.is_dir() else [p]
    return out[:limit] if limit else out


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine(device: Any) -> dict[str, Any]:
    import torch

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name()
    return {"cores": cores, "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "device": str(device), "device_name": name, "torch": torch.__version__,
            "load_average": [round(v, 2) for v in os.getloadavg()]}


def detectors(args: argparse.Namespace, device: Any) -> list[tuple[str, Any]]:
    from reeb_torch.detection import DetectorSettings, ReebDetector

    if args.detector:
        return [(f"{p.name} ({ReebDetector.load(p).settings.min_size} px)", ReebDetector.load(p, device))
                for p in args.detector]
    return [(f"untrained heads ({n} px)", ReebDetector(settings=DetectorSettings(min_size=n)).to(device).eval())
            for n in args.min_size]


def timed_pass(det: Any, stages: Any, images: list[Any], batch: int, device: Any) -> dict[str, float]:
    """Seconds per stage over all ``images`` in batches of ``batch``."""
    import torch

    before = dict(stages.seconds)
    total = 0.0
    for i in range(0, len(images), batch):
        t0 = time.perf_counter()
        det([im.to(device) for im in images[i:i + batch]])
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        total += time.perf_counter() - t0
    out = {k: stages.seconds[k] - before[k] for k in before}
    out["detector"] = total
    out["other"] = total - sum(out[k] for k in before)
    return out


def main(argv: list[str] | None = None) -> int:
    import torch

    from reeb_torch.io import read_image
    from reeb_torch.runs.detect_run import StageTimes

    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    paths = image_paths(args.images, args.limit)
    if not paths:
        raise SystemExit("no images")
    env = machine(device)
    dets = detectors(args, device)
    images = [read_image(p) for p in paths]
    runs: dict[tuple[int, int], list[dict[str, float]]] = {}
    timers = [StageTimes(det.model, device) for _, det in dets]
    for (_, det), batch in [(d, b) for d in dets for b in args.batch]:
        det(images[:batch])  # warm-up, not counted
    decode: list[float] = []
    for _ in range(args.repeats):
        for p in paths:
            t0 = time.perf_counter()
            read_image(p)
            decode.append(time.perf_counter() - t0)
        for k, ((_, det), timer) in enumerate(zip(dets, timers)):
            for batch in args.batch:
                runs.setdefault((k, batch), []).append(timed_pass(det, timer, images, batch, device))
    env["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
    decode_ms = 1000 * statistics.median(decode)
    rows = []
    for (k, batch), passes in runs.items():
        med = sorted(passes, key=lambda r: r["detector"])[(len(passes) - 1) // 2]  # the median pass (lower of two)
        ms = {s: round(1000 * med[s] / len(images), 1) for s in STAGES if s != "decode"}
        rows.append({"name": dets[k][0], "min_size": dets[k][1].settings.min_size, "batch": batch,
                     "decode": round(decode_ms, 1), **ms,
                     "serial_end_to_end": round(decode_ms + ms["detector"], 1),
                     "passes_ms": [round(1000 * r["detector"] / len(images), 1) for r in passes]})
    sizes = sorted({tuple(im.shape[-2:]) for im in images})
    command = rerun_line("benchmarks/detect_speed.py", sys.argv[1:] if argv is None else argv)
    lines = [f"# rerun: {command}",
             f"# {len(images)} images ({', '.join(f'{w}x{h}' for h, w in sizes)}), {args.repeats} passes, median pass; "
             f"ms per image",
             f"# machine: {env['cores']} cores ({env['device_name']}), torch {env['torch']} with "
             f"{env['torch_threads']} threads, device {env['device']}; load average {env['load_average']} before, "
             f"{env['load_average_after']} after",
             f"{'detector':<34}{'batch':>6}{'decode':>8}{'proposals':>10}{'backbone':>10}{'heads':>8}{'other':>8}"
             f"{'total':>10}{'+decode':>9}"]
    for r in rows:
        lines.append(f"{r['name'][:33]:<34}{r['batch']:>6}{r['decode']:>8.0f}{r['proposals']:>10.0f}"
                     f"{r['backbone']:>10.0f}{r['heads']:>8.0f}{r['other']:>8.0f}{r['detector']:>10.0f}"
                     f"{r['serial_end_to_end']:>9.0f}")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "speed.txt").write_text(text + "\n")
        (args.out / "speed.json").write_text(json.dumps(
            {"command": command, "images": [str(p) for p in paths], "repeats": args.repeats, "machine": env,
             "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
