"""Milliseconds per image of ``reeb detect``'s work, stage by stage, beside torchvision's mobile detectors.

For each detector (``--detector FILE`` or a shipped name, or ``--arm NAME="reeb detector fit
options"`` for a detector of those settings with untrained heads: the same computation as a
trained one but for the heads' NMS, which sees other scores) this runs what ``reeb detect``
runs on the decoded images: ``ReebDetector(images)`` on batches of ``--batch`` images, its
stages timed by its own clock (:class:`reeb_torch.detection.inference.StageClock`:
``proposals``, ``resize``, ``backbone``, ``neck``, ``roi_align``, ``box_head``,
``postprocess``). Decoding (:func:`reeb_torch.io.read_image`, which ``reeb detect``'s worker
processes run beside the detector) is timed apart. In the same run, interleaved, torchvision's
``fasterrcnn_mobilenet_v3_large_fpn`` and ``fasterrcnn_mobilenet_v3_large_320_fpn`` (built
with ``weights=None``: random weights cost the same time) run on the same images and batches
as the reference, and every detector is reported as a ratio of their time.

``--threads 1 2``: each pass runs once per count, the process bound to that many cores
(``os.sched_setaffinity``) with as many torch threads, so one-thread figures are one core's.
The first batch of each (model, batch, threads) is a warm-up; then ``--repeats`` passes, every
model in turn within a pass (a slow spell of a shared machine hits all alike); the median
pass is reported (of an even number, the faster of the middle two).

    python benchmarks/detect_speed.py ../shared/data/kitti/images --limit 12 --detector kitti \\
        --detector kitti@float32 --batch 1 8 --threads 1 2 --out docs/results/detector/speed

``FILE@float32`` runs a trained detector as a CPU without native bfloat16 does (its backbone
in float32, the same heads), in the same run as the native path.

Writes ``OUT/speed.txt`` and ``OUT/speed.json`` (per model, batch and threads: ms/img per
stage, the total, the ratio to each reference, every pass; the machine and its load).
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

REFERENCES = ("fasterrcnn_mobilenet_v3_large_fpn", "fasterrcnn_mobilenet_v3_large_320_fpn")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("images", nargs="*", type=Path, default=[REPO_ROOT / "examples" / "data"],
                   help="image files or folders (default: the bundled examples/data)")
    p.add_argument("--detector", action="append", default=[], metavar="FILE",
                   help="a detector file, or a shipped name such as kitti (repeat for several); FILE@float32: the "
                        "path a CPU without native bfloat16 gets; FILE@rankR: its box head factorised to rank R; "
                        "FILE@int8: its box head in int8 (combined: FILE@float32@rank128@int8)")
    p.add_argument("--arm", action="append", default=[], metavar='NAME="OPTIONS"',
                   help="a detector of these reeb detector fit options with untrained heads (repeatable)")
    p.add_argument("--batch", type=int, nargs="+", default=[1, 8], help="batch sizes (default: 1 8)")
    p.add_argument("--threads", type=int, nargs="+", default=[2], help="cores and torch threads (default: 2)")
    p.add_argument("--limit", type=int, help="only the first N images")
    p.add_argument("--repeats", type=int, default=3, help="timed passes over the images")
    p.add_argument("--reference", nargs="*", default=list(REFERENCES), choices=REFERENCES,
                   help="torchvision detectors timed beside (default: both; none with an empty list)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--out", type=Path, help="folder for speed.txt and speed.json")
    args = p.parse_args(argv)
    if not args.detector and not args.arm:
        p.error("give --detector FILE|NAME or --arm NAME=OPTIONS")
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

    from reeb_torch.detection.lite0 import native_bfloat16

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name()
    return {"cores": len(os.sched_getaffinity(0)), "cpu_count": os.cpu_count(), "device": str(device),
            "device_name": name, "torch": torch.__version__, "native_bfloat16": native_bfloat16(device),
            "load_average": [round(v, 2) for v in os.getloadavg()]}


def load_variant(spec: str, device: Any) -> Any:
    """``FILE[@float32][@rankR][@int8]``: the trained detector, loaded as a CPU without native
    bfloat16 loads it (``@float32``: ``REEB_NATIVE_BF16=0`` while it is built), with its box
    head factorised to rank R (``@rankR``: :meth:`~reeb_torch.detection.ReebDetector.
    factorise_box_head`) and/or in int8 (``@int8``: :meth:`~reeb_torch.detection.ReebDetector.
    quantise_box_head`), in the order given."""
    import warnings

    from reeb_torch.detection import ReebDetector

    path, *tags = spec.split("@")
    before = os.environ.get("REEB_NATIVE_BF16")
    try:
        if "float32" in tags:
            os.environ["REEB_NATIVE_BF16"] = "0"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the float32 path's notice
            det = ReebDetector.load(path, device)
    finally:
        if before is None:
            os.environ.pop("REEB_NATIVE_BF16", None)
        else:
            os.environ["REEB_NATIVE_BF16"] = before
    for tag in tags:
        if tag.startswith("rank"):
            det.factorise_box_head(int(tag[4:]))
        elif tag == "int8":
            det.quantise_box_head()
        elif tag != "float32":
            raise SystemExit(f"--detector {spec}: unknown variant {tag!r} (float32, rankR, int8)")
    return det


def ours(args: argparse.Namespace, device: Any) -> list[tuple[str, Any]]:
    """``(name, detector)`` of every ``--detector`` and ``--arm``."""
    from detector_paired import fit_options

    from reeb_torch.detection import ReebDetector
    from reeb_torch.detection.inference import StageClock
    from reeb_torch.runs.detector import fit_settings

    out = []
    for spec in args.detector:
        out.append((Path(spec).name, load_variant(spec, device)))
    for text in args.arm:
        name, _, options = text.partition("=")
        settings = fit_settings(fit_options([Path(".")], options))  # --crop-top auto: none, untrained
        out.append((name, ReebDetector(settings=settings, device=device).to(device).eval()))
    for _, det in out:
        det.clock = StageClock(device)
    return out


def references(names: list[str], device: Any) -> list[tuple[str, Any]]:
    import torchvision

    return [(n, getattr(torchvision.models.detection, n)(weights=None, weights_backbone=None).to(device).eval())
            for n in names]


def timed_pass(model: Any, images: list[Any], batch: int, device: Any, reference: bool) -> dict[str, float]:
    """Seconds over all ``images`` in batches of ``batch``: ``total`` and, for ours, per stage."""
    import torch

    clock = getattr(model, "clock", None)
    before = dict(clock.seconds) if clock is not None else {}
    total = 0.0
    with torch.no_grad():
        for i in range(0, len(images), batch):
            chunk = [im.to(device) for im in images[i:i + batch]]
            t0 = time.perf_counter()
            model([im.float() / 255 for im in chunk] if reference else chunk)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            total += time.perf_counter() - t0
    out = {k: clock.seconds[k] - before[k] for k in before} if clock is not None else {}
    out["total"] = total
    return out


def set_threads(n: int) -> None:
    import torch

    cores = sorted(os.sched_getaffinity(0) | _ALL)
    os.sched_setaffinity(0, set(cores[:n]))
    torch.set_num_threads(n)


_ALL: set[int] = set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else set()


def median_pass(passes: list[dict[str, float]]) -> dict[str, float]:
    return sorted(passes, key=lambda r: r["total"])[(len(passes) - 1) // 2]


def main(argv: list[str] | None = None) -> int:
    import torch

    from reeb_torch.io import read_image

    args = parse_args(argv)
    device = torch.device(args.device)
    paths = image_paths(args.images, args.limit)
    if not paths:
        raise SystemExit("no images")
    env = machine(device)
    models = [(n, m, False) for n, m in ours(args, device)] + [(n, m, True) for n, m in references(args.reference,
                                                                                                  device)]
    images = [read_image(p) for p in paths]
    runs: dict[tuple[str, int, int], list[dict[str, float]]] = {}
    for threads in args.threads:
        set_threads(threads)
        for (name, model, ref), batch in [(m, b) for m in models for b in args.batch]:
            timed_pass(model, images[:batch], batch, device, ref)  # warm-up, not counted
    decode: list[float] = []
    for _ in range(args.repeats):
        for p in paths:
            t0 = time.perf_counter()
            read_image(p)
            decode.append(time.perf_counter() - t0)
        for threads in args.threads:
            set_threads(threads)
            for name, model, ref in models:
                for batch in args.batch:
                    runs.setdefault((name, batch, threads), []).append(timed_pass(model, images, batch, device, ref))
    set_threads(max(args.threads))
    env["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
    n = len(images)
    decode_ms = round(1000 * statistics.median(decode), 1)
    rows = []
    for (name, batch, threads), passes in runs.items():
        med = median_pass(passes)
        rows.append({"name": name, "batch": batch, "threads": threads, "reference": name in REFERENCES,
                     **{k: round(1000 * v / n, 1) for k, v in med.items()},
                     "passes_ms": [round(1000 * r["total"] / n, 1) for r in passes]})
    for r in rows:
        for ref in args.reference:
            other = next(x for x in rows if x["name"] == ref and x["batch"] == r["batch"]
                         and x["threads"] == r["threads"])
            r[f"ratio_{ref}"] = round(r["total"] / other["total"], 3)
    text = report(rows, args, env, decode_ms, n, sys.argv[1:] if argv is None else argv)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "speed.txt").write_text(text + "\n")
        (args.out / "speed.json").write_text(json.dumps(
            {"command": rerun_line("benchmarks/detect_speed.py", sys.argv[1:] if argv is None else argv),
             "images": [str(p) for p in paths], "repeats": args.repeats, "decode_ms": decode_ms, "machine": env,
             "rows": rows}, indent=2) + "\n")
    return 0


def report(rows: list[dict[str, Any]], args: argparse.Namespace, env: dict[str, Any], decode_ms: float, n: int,
           argv: list[str]) -> str:
    from reeb_torch.detection.inference import STAGES

    short = {"proposals": "REEB", "resize": "resize", "backbone": "backbone", "neck": "neck", "roi_align": "RoI",
             "box_head": "head", "postprocess": "post"}
    refs = {r: ("FPN" if r.endswith("large_fpn") else "320") for r in args.reference}
    head = (f"{'model':<34}{'batch':>6}{'thr':>4}" + "".join(f"{short[s]:>9}" for s in STAGES) + f"{'total':>9}"
            + "".join(f"{'x ' + refs[r]:>8}" for r in args.reference))
    lines = [f"# rerun: {rerun_line('benchmarks/detect_speed.py', argv)}",
             f"# {n} images, {args.repeats} passes, median pass; ms per image (decoding apart: {decode_ms} ms, in "
             f"reeb detect's worker processes); x FPN / x 320: our time over torchvision's "
             "fasterrcnn_mobilenet_v3_large_fpn / _320_fpn, same images, batch and cores",
             f"# machine: {env['cores']} cores ({env['device_name']}), native bfloat16 {env['native_bfloat16']}, "
             f"torch {env['torch']}, device {env['device']}; load average {env['load_average']} before, "
             f"{env['load_average_after']} after", head]
    for r in rows:
        cells = "".join(f"{r[s]:>9.1f}" if s in r else f"{'':>9}" for s in STAGES)
        ratios = "".join(f"{r[f'ratio_{ref}']:>8.2f}" for ref in args.reference)
        lines.append(f"{r['name'][:33]:<34}{r['batch']:>6}{r['threads']:>4}{cells}{r['total']:>9.1f}{ratios}")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
