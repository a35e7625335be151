"""Evaluation of proposals on KITTI-format folders, shipped with the package.

- :mod:`reeb_torch.eval.table3`: the paper's Table 3 (recall at 500/1000/2000 proposals
  and IoU 0.3/0.5/0.7 for REEB and the classical baselines), with the KITTI-moderate and
  per-class tables; what ``reeb eval`` and ``benchmarks/table3.py`` run.
- :mod:`reeb_torch.eval.data`: the KITTI reader (images, ``label_2`` files, calibration).
- :mod:`reeb_torch.eval.metrics`: recall, AR, the paired sign test, bootstrap intervals.
- :mod:`reeb_torch.eval.baselines`: Edge Boxes, BING and Selective Search (OpenCV contrib).
- :mod:`reeb_torch.eval.common`: ``--frames`` ranges, loading a KITTI folder, the rerun
  line and the machine's description.

>>> from reeb_torch.eval import table3
>>> record = table3.main(["--data", "kitti/", "--limit", "10", "--methods", "reeb-default"])
>>> record["methods"]["reeb-default"]["recall"]["micro"]["2000"]["0.7"]

From a shell: ``reeb eval kitti/ --limit 10`` or ``python -m reeb_torch.eval --data kitti/``.
"""

from __future__ import annotations

from . import common, table3
from .common import FrameRange, load_kitti, parse_frame_range, select_frames
from .table3 import METHODS, main

__all__ = [
    "common",
    "table3",
    "main",
    "METHODS",
    "FrameRange",
    "parse_frame_range",
    "select_frames",
    "load_kitti",
]
