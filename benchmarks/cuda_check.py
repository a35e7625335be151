"""One prepared run for a machine with a GPU: the CUDA tests, the CUDA path's boxes against the
CPU's, and images a second at batch 1 and 8 for the default, ``training-free`` and the
shipped detector, written to ``--out`` (``cuda_check.txt`` and ``.json``).

    python benchmarks/cuda_check.py --out docs/results/cuda            # on the GPU machine
    python benchmarks/cuda_check.py --device cpu --limit 2 --no-tests  # the script's own check

The boxes: per preset, on ``--limit`` frames of ``--data`` (their commonest size), the share of
frames whose boxes are the CPU's bit for bit, the share of the CPU's best 200 boxes with a
CUDA box at IoU > 0.99, and recall @2000 / IoU 0.7 on both devices (the tensor ops on CUDA
round the prefilter and the MLP otherwise than the CPU's kernels: near, not equal, is what
the tests ask). Speed: the median of ``--repeats`` timed passes after a warm-up, the device
synchronised around each; the detector with the file's own settings (``reeb detect``'s).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, default_kitti_dir, environment, rerun_line, write_outputs  # noqa: E402

PRESETS = ("default", "training-free", "paper")
"""The presets whose boxes are compared."""

TIMED = ("default", "training-free")
"""The presets timed."""


def frames(data: Path, limit: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Up to ``limit`` frames of the KITTI-format folder ``data`` of its commonest image size,
    ``uint8 (3, H, W)`` each, and their target boxes ``float32 [N, 4]``."""
    from reeb_torch.datasets.folders import load_kitti

    items = load_kitti(data)[0]
    size = Counter(tuple(it["image"].shape[-2:]) for it in items).most_common(1)[0][0]
    keep = [it for it in items if tuple(it["image"].shape[-2:]) == size][:limit]
    return [it["image"] for it in keep], [it["boxes"].float() for it in keep]


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def cuda_tests() -> dict:
    """``pytest -m cuda`` over the tests: its exit code and last line."""
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "cuda", "tests"], check=False,
                         cwd=REPO_ROOT,
                         capture_output=True, text=True)
    lines = [ln for ln in run.stdout.splitlines() if ln.strip()]
    return {"returncode": run.returncode, "summary": lines[-1] if lines else run.stderr.strip()[-300:]}


def boxes_agree(images: list[torch.Tensor], gts: list[torch.Tensor], device: str) -> dict:
    """Per preset of :data:`PRESETS`: the CUDA path's boxes against the CPU's (module doc)."""
    from torchvision.ops import box_iou

    from reeb_torch import ProposalGenerator, get_preset
    from reeb_torch.metrics.recall import object_hits

    out = {}
    for name in PRESETS:
        gen = ProposalGenerator(get_preset(name))
        cpu = [gen([im])[0] for im in images]
        gen = gen.to(device)
        dev = [{k: v.cpu() for k, v in gen([im.to(device)])[0].items()} for im in images]
        same = sum(torch.equal(a["boxes"], b["boxes"]) and torch.equal(a["scores"], b["scores"])
                   for a, b in zip(cpu, dev))
        near = [float((box_iou(a["boxes"][:200], b["boxes"][:200]).amax(1) > 0.99).float().mean())
                for a, b in zip(cpu, dev) if len(a["boxes"]) and len(b["boxes"])]
        hits = [object_hits([o["boxes"] for o in outs], gts, 2000, 0.7) for outs in (cpu, dev)]
        objects = sum(len(g) for g in gts)
        out[name] = {"frames": len(images), "identical": same,
                     "top200_matched": statistics.fmean(near) if near else float("nan"),
                     "recall_cpu": 100 * sum(int(h.sum()) for h in hits[0]) / max(objects, 1),
                     "recall_device": 100 * sum(int(h.sum()) for h in hits[1]) / max(objects, 1)}
    return out


def _images_per_second(run, batch: list[torch.Tensor], device: str, repeats: int) -> float:
    run(batch)  # the warm-up: kernels, caches, cuDNN's choices
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        run(batch)
        _sync(device)
        times.append(time.perf_counter() - t0)
    return len(batch) / statistics.median(times)


def speed(images: list[torch.Tensor], device: str, repeats: int, detector: str | None) -> dict:
    """Images a second at batch 1 and 8 (frames repeated to fill a batch) per preset of
    :data:`TIMED` and for ``detector`` (a shipped name or file; None: not timed)."""
    from reeb_torch import ProposalGenerator, get_preset

    on = [im.to(device) for im in images]
    batches = {b: [on[j % len(on)] for j in range(b)] for b in (1, 8)}
    out: dict = {}
    with torch.no_grad():
        for name in TIMED:
            gen = ProposalGenerator(get_preset(name)).to(device)
            out[name] = {str(b): _images_per_second(gen, x, device, repeats) for b, x in batches.items()}
        if detector is not None:
            from reeb_torch.detection import ReebDetector

            det = ReebDetector.load(detector, device=device)
            out[f"detector {detector}"] = {
                str(b): _images_per_second(det, x, device, repeats)
                for b, x in batches.items()}
    return out


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_kitti_dir(), help="a KITTI-format folder")
    ap.add_argument("--device", default="cuda", help="cuda, cuda:N, or cpu (the script's own check)")
    ap.add_argument("--limit", type=int, default=8, help="frames compared and timed")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per batch size")
    ap.add_argument("--detector", default="kitti", help="the detector timed ('none': no detector)")
    ap.add_argument("--no-tests", action="store_true", help="leave out pytest -m cuda")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("no CUDA device here (torch.cuda.is_available() is False); --device cpu checks the script")
    head = f"# rerun: {rerun_line('benchmarks/cuda_check.py', argv if argv is not None else sys.argv[1:])}"
    print(head, flush=True)
    record: dict = {"environment": environment(), "device": args.device}
    if args.device.startswith("cuda"):
        record["device_name"] = torch.cuda.get_device_name(args.device)
    if not args.no_tests:
        record["tests"] = cuda_tests()
    images, gts = frames(args.data, args.limit)
    record["boxes"] = boxes_agree(images, gts, args.device)
    record["speed"] = speed(images, args.device, args.repeats, None if args.detector == "none" else args.detector)
    text = [head, f"# device {record.get('device_name', args.device)}; {len(images)} frames of {args.data}"]
    if "tests" in record:
        text.append(f"pytest -m cuda: exit {record['tests']['returncode']}: {record['tests']['summary']}")
    text.append("boxes against the CPU's: preset, frames identical, CPU's best 200 matched at IoU > 0.99, "
                "recall @2000 / IoU 0.7 CPU / device")
    for name, r in record["boxes"].items():
        text.append(f"  {name:14s} {r['identical']}/{r['frames']}  {100 * r['top200_matched']:.1f} %  "
                    f"{r['recall_cpu']:.1f} / {r['recall_device']:.1f} %")
    text.append("images a second (median of the passes): batch 1, batch 8")
    for name, r in record["speed"].items():
        text.append(f"  {name:22s} {r['1']:8.1f} {r['8']:8.1f}")
    for line in text[1:]:
        print(line)
    return write_outputs(args.out, "cuda_check", text, record)


if __name__ == "__main__":
    main()
