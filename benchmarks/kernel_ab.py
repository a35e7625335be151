"""One compiled kernel of this checkout against the same kernel at another git revision:
the same inputs, alternated calls, paired, and whether the outputs are the same bits.

End-to-end runs (``speed_ab.py``) cannot see a change worth a few per cent of one stage:
a shared machine drifts more than that between runs. Here the kernel's real inputs are captured
from the pipeline (``--frames`` KITTI frames at ``--batch``, on one core, so that each
call covers its whole batch), then both versions run on copies of them in turns, in the
same process: ``--reps`` rounds, the order alternating from round to round, each round
timing every captured call of one version on its own warm copy of the inputs. The two
versions are compiled here from their sources without the on-disk cache, alike. The
outputs compared are every array argument after the call (the kernels write into their
arguments) and the returned values, on fresh copies.

Reports each version's median ms per round, the median of the rounds' ratios (this /
base), how many rounds favour each side and the exact sign-test p.

Rerun: ``python benchmarks/kernel_ab.py stages.scoring._integral_kernel --base REV
[--frames 8] [--batch 8] [--reps 20] [--preset default] [--data DIR]``
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, default_kitti_dir, paired_ratios, rerun_line  # noqa: E402


def kernel_source(module: str, rev: str | None) -> str:
    """The source of ``reeb_torch.<module>`` in the working tree, or at git revision ``rev``."""
    path = Path("reeb_torch", *module.split(".")).with_suffix(".py")
    if rev is None:
        return (REPO_ROOT / path).read_text()
    return subprocess.run(["git", "show", f"{rev}:{path.as_posix()}"], cwd=REPO_ROOT, check=True,
                          capture_output=True, text=True).stdout


def compile_kernel(module: str, name: str, source: str, tag: str) -> Callable:
    """``name`` from ``source`` run as a sibling module of ``reeb_torch.<module>`` (its
    relative imports resolve to the installed package), with numba's cache off."""
    package = "reeb_torch." + module.rsplit(".", 1)[0] if "." in module else "reeb_torch"
    mod = types.ModuleType(f"{package}._ab_{tag}")
    mod.__package__ = package
    sys.modules[mod.__name__] = mod
    exec(compile(source.replace("cache=True", "cache=False"), f"<{tag} {module}>", "exec"), mod.__dict__)
    return getattr(mod, name)


def capture(module: str, name: str, images: list, batch: int, preset: str) -> list[tuple]:
    """The arguments of every call of ``reeb_torch.<module>.<name>`` while the preset's
    generator runs ``images`` in batches of ``batch`` on one core (arrays copied)."""
    from reeb_torch import ProposalGenerator, get_preset
    from reeb_torch.stages._threads import serially

    mod = importlib.import_module(f"reeb_torch.{module}")
    real = getattr(mod, name)
    gen = ProposalGenerator(get_preset(preset))
    gen(images[:batch])  # warm-up: kernels, the image size's tables
    calls: list[tuple] = []

    def spy(*args: Any) -> Any:
        calls.append(tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args))
        return real(*args)

    setattr(mod, name, spy)
    try:
        with serially():
            for i in range(0, len(images), batch):
                gen(images[i: i + batch])
    finally:
        setattr(mod, name, real)
    return calls


def _copies(calls: list[tuple]) -> list[list]:
    return [[a.copy() if isinstance(a, np.ndarray) else a for a in args] for args in calls]


def outputs(fn: Callable, args: list) -> list[np.ndarray]:
    """Every array argument after ``fn(*args)``, then the returned arrays and numbers."""
    ret = fn(*args)
    out = [a for a in args if isinstance(a, np.ndarray)]
    for r in ret if isinstance(ret, tuple) else (ret,):
        if r is not None:
            out.append(np.asarray(r))
    return out


def same_bits(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    """Whether two lists of arrays hold the same shapes, types and bytes."""
    return len(a) == len(b) and all(x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
                                    for x, y in zip(a, b))


def race(fns: dict[str, Callable], calls: list[tuple], reps: int) -> dict[str, list[float]]:
    """``reps`` rounds, the versions' order alternating: ms of each version over every
    call. Each version has its own copy of the inputs, made once and used in every round
    (warm, as the pipeline's reused buffers are; a fresh copy per round made whichever
    version ran second in a round 1.7× slower), after one untimed round."""
    args = {k: _copies(calls) for k in fns}
    times: dict[str, list[float]] = {k: [] for k in fns}
    names = list(fns)
    for r in range(reps + 1):
        for k in names if r % 2 == 0 else names[::-1]:
            t0 = time.perf_counter()
            for a in args[k]:
                fns[k](*a)
            if r > 0:
                times[k].append((time.perf_counter() - t0) * 1000)
    return times


def summarise(times: dict[str, list[float]]) -> dict:
    """Medians, the rounds' ratios (this / base), wins each way and the sign-test p."""
    ratios, faster, slower, p = paired_ratios(times["base"], times["this"])
    return {"base_ms": round(statistics.median(times["base"]), 4), "this_ms": round(statistics.median(times["this"]), 4),
            "median_ratio": round(statistics.median(ratios), 3), "faster": faster, "slower": slower,
            "sign_p": round(p, 4)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kernel", help="module.name under reeb_torch, e.g. stages.scoring._integral_kernel")
    ap.add_argument("--base", required=True, help="git revision to compare with")
    ap.add_argument("--data", type=Path, default=default_kitti_dir())
    ap.add_argument("--frames", type=int, default=8, help="the first frames; those of their commonest size are used")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--preset", default="default")
    args = ap.parse_args(argv)
    from reeb_torch.datasets.kitti import KittiDataset
    from reeb_torch.io import read_image

    print("# rerun:", rerun_line("benchmarks/kernel_ab.py", argv if argv is not None else sys.argv[1:]))
    module, name = args.kernel.rsplit(".", 1)
    images = [read_image(f) for f in KittiDataset(args.data, limit=args.frames).image_paths]
    shapes = [im.shape for im in images]
    size = max(set(shapes), key=shapes.count)
    images = [im for im in images if im.shape == size]  # the commonest image size: one set of tables
    calls = capture(module, name, images, args.batch, args.preset)
    if not calls:
        raise SystemExit(f"{args.kernel} was not called by the {args.preset!r} preset from Python")
    fns = {"base": compile_kernel(module, name, kernel_source(module, args.base), "base"),
           "this": compile_kernel(module, name, kernel_source(module, None), "this")}
    same = all(same_bits(outputs(fns["base"], a), outputs(fns["this"], a2))
               for a, a2 in zip(_copies(calls), _copies(calls)))
    res = summarise(race(fns, calls, args.reps))
    res.update(kernel=args.kernel, base=args.base, calls=len(calls), images=len(images), same_outputs=same)
    print(f"{args.kernel}: {len(calls)} calls from {len(images)} frames at batch {args.batch} ({args.preset}); "
          f"outputs {'the same bits' if same else 'DIFFER'}")
    print(f"{args.base} {res['base_ms']} ms, this {res['this_ms']} ms per round; median ratio {res['median_ratio']} "
          f"(this / {args.base}); faster in {res['faster']}, slower in {res['slower']} of {args.reps} rounds "
          f"(sign test p = {res['sign_p']})")
    return res


if __name__ == "__main__":
    main()
