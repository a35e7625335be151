"""Evaluation of proposals on KITTI-format folders, shipped with the package (on the KITTI
reader of :mod:`reeb_torch.datasets.kitti` and the measures of :mod:`reeb_torch.metrics`).

- :mod:`reeb_torch.eval.methods`: its rows (REEB's presets, the baselines) and options;
- :mod:`reeb_torch.eval.table3`: the paper's Table 3 computed (recall at 500/1000/2000
  proposals and IoU 0.3/0.5/0.7 for REEB and the classical baselines, KITTI-moderate and
  per-class tables, AR, intervals, pairings);
- :mod:`reeb_torch.eval.report`: the table rendered (text, CSV, JSON) and written;
- :mod:`reeb_torch.eval.plots`: its two recall plots (matplotlib);
- :mod:`reeb_torch.eval.command`: ``reeb eval``, the click command over them;
- :mod:`reeb_torch.eval.baselines`: Edge Boxes, BING and Selective Search (OpenCV contrib);
- :mod:`reeb_torch.eval.common`: the rerun line and the machine's description.

The evaluation is the research wing: the product (the generator, the ranking and its fit,
the detectors, ``reeb tune``) imports none of it; ``reeb eval`` is its command.

>>> from reeb_torch.eval import Table3Options, run_table3
>>> record = run_table3(Table3Options(data=["kitti/"], limit=10, methods=["reeb-default"]), "runs/table3")
>>> record["methods"]["reeb-default"]["recall"]["micro"]["2000"]["0.7"]

From a shell: ``reeb eval kitti/ --limit 10``.

Importing this package imports neither torch nor OpenCV (``reeb --help`` stays quick);
:mod:`.table3` and the rest import them.
"""

from __future__ import annotations

from .command import run_table3
from .methods import METHODS, Table3Options

__all__ = [
    "run_table3",
    "Table3Options",
    "METHODS",
]
