"""Helpers of the evaluation: the rerun line, the machine, short lists of names."""

from __future__ import annotations

import os
import platform
import shlex
import sys
from collections.abc import Sequence
from typing import Any

__all__ = [
    "first_few",
    "rerun_line",
    "environment",
]


def first_few(names: Sequence[str], n: int = 8) -> str:
    """``names`` joined with commas, the first ``n`` of them and how many more."""
    shown = ", ".join(list(names)[:n])
    return shown + (f" and {len(names) - n} more" if len(names) > n else "")


def rerun_line(prog: str, argv: Sequence[str]) -> str:
    """The shell command that reruns ``prog`` with ``argv`` (``python prog`` for a script)."""
    head = ["python", prog] if prog.endswith(".py") else shlex.split(prog)
    return " ".join([*head, *map(shlex.quote, argv)])


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

