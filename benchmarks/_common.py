"""Helpers shared by the benchmark scripts: default paths, the rerun line, the machine."""

from __future__ import annotations

import os
import platform
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

__all__ = ["REPO_ROOT", "default_kitti_dir", "rerun_line", "environment", "timed"]

REPO_ROOT = Path(__file__).resolve().parents[1]
"""The repository root (the folder holding ``benchmarks/``)."""


def default_kitti_dir() -> Path:
    """``shared/data/kitti`` beside the repository: the 60 KITTI frames of the project."""
    return REPO_ROOT.parent / "shared" / "data" / "kitti"


def rerun_line(script: str, argv: Sequence[str]) -> str:
    """The shell command that reruns ``script`` with ``argv``, from the repository root."""
    return " ".join(["python", script, *map(shlex.quote, argv)])


def environment() -> dict[str, Any]:
    """Versions, thread counts and CPU of this run, for the JSON record."""
    import cv2
    import torch

    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.is_available(),
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
    }


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """Call ``fn()`` and return ``(result, wall seconds)`` (``time.perf_counter``)."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0
