"""Speed of this checkout against another git revision, in alternated runs, paired.

On a shared machine whole runs drift by a fifth or more in minutes (the 2-core machine of
``docs/results.md`` moved by a third between hours), more than most changes are worth. So this
runs the two versions in turns, each in its own process on the same frames (the other
revision from a temporary ``git worktree``; the kernel cache is keyed by source, so the
two share it), and reports each pair's ratio (this / base), their median, how many pairs
favour each side, and the exact two-sided sign-test p of that count
(``_common.paired_ratios``). A pair is two runs minutes apart, so a drift within a pair
still reaches the ratio; more pairs make it average out.

Each run: every frame at ``--batch`` sizes (default 8 and 1), ``--input`` uint8 (default) or
float32 in [0, 1] (as torchvision detectors pass them), after a warm-up
pass (compiling or loading the kernels, building each image size's tables), the best of
``--passes`` passes, ms per image.

With ``--first-call``, each run is instead the one-time cost a fresh install pays:
``reeb_torch.warmup()`` of ``--preset`` with an empty kernel cache of its own, in seconds,
with its helper process (``--one-process``: without it, all of the compile work in one
process).

Rerun: ``python benchmarks/speed_ab.py --base REV [--pairs 6] [--data DIR] [--preset default]
[--input float] [--first-call [--one-process]]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import default_kitti_dir, paired_ratios, rerun_line  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def summarise(pairs: list[tuple[dict[str, float], dict[str, float]]]) -> dict[str, dict]:
    """Per batch size: each pair's ratio (this / base), their median, the pairs where this
    checkout is faster and slower, the sign-test p, and both sides' ranges."""
    out = {}
    for key in pairs[0][0]:
        ratios, faster, slower, p = paired_ratios([base[key] for base, _ in pairs], [new[key] for _, new in pairs])
        out[key] = {"ratios": [round(r, 3) for r in ratios], "median_ratio": round(statistics.median(ratios), 3),
                    "faster": faster, "slower": slower, "sign_p": round(p, 3),
                    "base_ms": [round(b[key], 2) for b, _ in pairs], "this_ms": [round(n[key], 2) for _, n in pairs]}
    return out


def _child(data: str, preset: str, batches: list[int], passes: int, limit: int | None, kind: str) -> None:
    """One run (in a process of its own, with the version under test first on the path)."""
    from reeb_torch import ProposalGenerator, get_preset
    from reeb_torch.datasets.kitti import KittiDataset
    from reeb_torch.io import read_image

    paths = KittiDataset(data).image_paths[:limit]
    images = [read_image(p) for p in paths]
    if kind == "float":
        images = [x.float().div_(255.0) for x in images]
    gen = ProposalGenerator(get_preset(preset))
    result = {}
    for b in batches:
        def one_pass() -> float:
            t0 = time.perf_counter()
            for i in range(0, len(images), b):
                gen(images[i: i + b])
            return (time.perf_counter() - t0) / len(images) * 1e3

        one_pass()  # warm-up: kernels, each size's tables
        result[f"batch {b}"] = min(one_pass() for _ in range(passes))
    print(json.dumps(result))


def _first_call(preset: str) -> None:
    """One fresh install's warm-up of ``preset`` (in a process of its own, its cache folder
    empty)."""
    from reeb_torch import get_preset, warmup

    print(json.dumps({"first call, s": warmup(get_preset(preset), quiet=True)}))


def _run(src: Path, args: argparse.Namespace) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    if args.first_call:
        with tempfile.TemporaryDirectory(prefix="reeb-cache-") as cache:
            env["REEB_TORCH_CACHE_DIR"] = cache
            if args.one_process:
                env["REEB_TORCH_WARM_HELPER"] = "1"
            out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child-first-call", "--preset",
                                  args.preset], env=env, cwd=src, capture_output=True, text=True, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--data", str(args.data.resolve()),
           "--preset", args.preset, "--input", args.input,
           "--passes", str(args.passes), "--batch", *map(str, args.batch)]
    if args.limit:
        cmd += ["--limit", str(args.limit)]
    out = subprocess.run(cmd, env=env, cwd=src, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", help="git revision to compare with (required unless --child)")
    ap.add_argument("--pairs", type=int, default=6)
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--preset", default="default")
    ap.add_argument("--batch", type=int, nargs="+", default=[8, 1])
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--input", choices=("uint8", "float"), default="uint8")
    ap.add_argument("--first-call", action="store_true", help="time a fresh install's warm-up instead")
    ap.add_argument("--one-process", action="store_true", help="with --first-call: no helper process")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-first-call", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_first_call:
        _first_call(args.preset)
        return {}
    if args.child:
        _child(str(args.data), args.preset, args.batch, args.passes, args.limit, args.input)
        return {}
    if not args.base:
        ap.error("--base REV is required")
    rev = subprocess.run(["git", "rev-parse", "--short", args.base], cwd=REPO, capture_output=True, text=True,
                         check=True).stdout.strip()
    pairs = []
    with tempfile.TemporaryDirectory(prefix="reeb-ab-") as tmp:
        tree = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", "-f", str(tree), rev], cwd=REPO, check=True,
                       capture_output=True)
        try:
            for i in range(args.pairs):
                base = _run(tree, args)
                new = _run(REPO, args)
                pairs.append((base, new))
                print(f"pair {i + 1}: " + ", ".join(f"{k} {base[k]:.2f} -> {new[k]:.2f}" for k in base), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, capture_output=True)
    summary = summarise(pairs)
    print("# rerun:", rerun_line("benchmarks/speed_ab.py", sys.argv[1:] if argv is None else argv))
    if args.first_call:
        print(f"# this checkout against {rev}, {args.pairs} alternated pairs, warmup() of {args.preset} on an "
              f"empty kernel cache, s ({'one process' if args.one_process else 'with its helper process'})")
    else:
        print(f"# this checkout against {rev}, {args.pairs} alternated pairs, {args.preset}, {args.input} input, "
              f"ms/img (best of {args.passes} passes each)")
    for key, s in summary.items():
        print(f"{key}: median ratio {s['median_ratio']} (this / {rev}); faster in {s['faster']}, slower in "
              f"{s['slower']} of {args.pairs} pairs (sign test p = {s['sign_p']}); {rev} "
              f"{min(s['base_ms'])}-{max(s['base_ms'])}, this {min(s['this_ms'])}-{max(s['this_ms'])}")
    return summary


if __name__ == "__main__":
    main()
