"""How much the detector's frozen backbone maps change with the CPU's kernels: per precision,
the maps of the same frames computed under other thread counts and instruction sets.

A detector's heads train on the frozen EfficientNet-Lite0's maps of each frame, kept in the
cache as float16 (:mod:`reeb_torch.detection.feature_cache`). Those maps depend on how the
convolutions sum: on the thread count (each thread's part is summed apart) and on the kernels
the CPU's instruction set selects. Each ``--case`` computes the maps of the first ``--limit``
images in a fresh process, with its torch thread count and environment (``ONEDNN_MAX_CPU_ISA``
caps the instruction set oneDNN may use, as an older CPU has it), and every case is compared
with the first of its precision: the share of the cached float16 values that differ, the
largest difference, and the relative L2 distance over all values.

    python benchmarks/map_spread.py ../shared/data/kitti/images --limit 6 \\
        --out docs/results/detector/map_spread

Writes ``OUT/spread.txt`` (the table) and ``OUT/spread.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line  # noqa: E402

CASES = ("bfloat16:2", "bfloat16:1", "bfloat16:2:AVX512_CORE", "float32:2", "float32:1", "float32:2:AVX2",
         "float32:1:AVX2")
"""``PRECISION:THREADS[:ISA]``; the first of each precision is its reference."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("images", type=Path, help="a folder of images")
    p.add_argument("--limit", type=int, default=6, help="the first N images (default 6)")
    p.add_argument("--case", nargs="+", default=list(CASES), metavar="PRECISION:THREADS[:ISA]",
                   help="the computations compared; ISA: ONEDNN_MAX_CPU_ISA's value")
    p.add_argument("--crop-top", type=float, default=0.25, help="the share of rows the backbone skips (default 0.25)")
    p.add_argument("--out", type=Path, required=True, help="folder for spread.txt and spread.json")
    p.add_argument("--maps", help=argparse.SUPPRESS)  # the child's: PRECISION THREADS OUT
    return p.parse_args(argv)


def child(args: argparse.Namespace) -> None:
    """Compute the maps in this process (``--maps PRECISION:THREADS:FILE``) and save them."""
    import torch

    from reeb_torch.detection import DetectorSettings, ReebDetector
    from reeb_torch.detection.feature_cache import compute_features
    from reeb_torch.io import read_image

    precision, threads, out = args.maps.split(":", 2)
    torch.set_num_threads(int(threads))
    det = ReebDetector(settings=DetectorSettings(precision=precision, crop_top=args.crop_top))
    paths = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))[:args.limit]
    maps = {}
    with torch.no_grad():
        for i, p in enumerate(paths):
            for level, v in compute_features(det.model, read_image(p), args.crop_top).levels.items():
                maps[f"{i}/{level}"] = v
    torch.save({"maps": maps, "runs": det.precision}, out)


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, float]:
    """The share of values that differ, the largest difference and the relative L2 distance of
    ``b``'s maps to ``a``'s (float16 values, as cached)."""
    n = differ = 0
    largest = num = den = 0.0
    for k, x in a.items():
        x, y = x.float(), b[k].float()
        n += x.numel()
        differ += int((x != y).sum())
        largest = max(largest, float((x - y).abs().max()))
        num += float(((x - y) ** 2).sum())
        den += float((x ** 2).sum())
    return {"differ_pct": round(100 * differ / n, 4), "max_abs": round(largest, 5),
            "rel_l2": float(f"{(num / den) ** 0.5:.3g}") if den else 0.0}


def main(argv: list[str] | None = None) -> int:
    import torch

    args = parse_args(argv)
    if args.maps:
        child(args)
        return 0
    rows: list[dict[str, Any]] = []
    refs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.case:
            precision, threads, *isa = case.split(":")
            out = Path(tmp) / f"{len(rows)}.pt"
            env = {k: v for k, v in os.environ.items() if k != "ONEDNN_MAX_CPU_ISA"}
            if isa:
                env["ONEDNN_MAX_CPU_ISA"] = isa[0]
            subprocess.run([sys.executable, __file__, str(args.images), "--limit", str(args.limit), "--crop-top",
                            str(args.crop_top), "--out", str(args.out), "--maps", f"{precision}:{threads}:{out}"],
                           check=True, env=env)
            got = torch.load(out, weights_only=True)
            ref = refs.setdefault(precision, got)
            rows.append({"case": case, "precision": precision, "threads": int(threads), "isa": isa[0] if isa else "",
                         "runs": got["runs"], "reference": next(c for c in args.case if c.split(":")[0] == precision),
                         **compare(ref["maps"], got["maps"])})
        cross = compare(refs["float32"]["maps"], refs["bfloat16"]["maps"]) if len(refs) == 2 else None
    lines = [f"# rerun: {rerun_line('benchmarks/map_spread.py', sys.argv[1:] if argv is None else argv)}",
             f"# {args.limit} images of {args.images}; maps as the cache keeps them (float16); each case against "
             "the first of its precision", "",
             f"{'case (precision:threads:ISA cap)':36s} {'runs as':9s} {'values differing':>17s} {'largest':>8s} "
             f"{'relative L2':>12s}"]
    for r in rows:
        lines.append(f"{r['case']:36s} {r['runs']:9s} {r['differ_pct']:16.4f}% {r['max_abs']:8.4f} {r['rel_l2']:12.3g}")
    if cross:
        lines += ["", f"bfloat16 against float32 maps ({args.case[0]} and the first float32 case): "
                      f"{cross['differ_pct']:.2f} % of values differ, relative L2 {cross['rel_l2']:.3g}"]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "spread.txt").write_text("\n".join(lines) + "\n")
    (args.out / "spread.json").write_text(json.dumps({"rows": rows, "bfloat16_vs_float32": cross,
                                                      "environment": environment()}, indent=2) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
