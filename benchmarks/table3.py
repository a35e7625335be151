"""The paper's Table 3 on a KITTI-format folder: recall of REEB and of the classical baselines.

A thin script over :mod:`reeb_torch.eval.table3` (the same code ``reeb eval`` runs from an
installed package); see there for the methods, the tables (all objects - the headline -,
KITTI-moderate objects, class mean, per-class recall at 2000 / IoU 0.7, AR) and the files
written into ``--out`` (default ``runs/table3``): ``table3.txt``, ``table3.csv``,
``table3.json`` and two plots.

Rerun: ``python benchmarks/table3.py [--data DIR ...] [--limit N] [--frames A:B ...]
[--methods ...] [--cross-validate FOLDS] [--leave-folder-out]`` (the README's table:
``--cross-validate 10 --leave-folder-out --out docs/results/table3``); ``--data`` defaults to the two dev folders beside the repository,
``../shared/data/kitti`` and ``../shared/data/kitti_tracking``: every table is given for
each folder and for both together. ``--frames`` selects numeric ids (KITTI object frames;
select tracking frames by folder).
From code, ``main(argv)`` (returns the JSON record).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Sequence

try:  # imported as benchmarks.table3
    from ._common import REPO_ROOT, default_dev_dirs
except ImportError:  # run as a script, or loaded from its file
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import REPO_ROOT, default_dev_dirs  # type: ignore[no-redef]

    # The checkout's package first: run from benchmarks/, an editable install made before
    # reeb_torch/__init__.py existed resolves `reeb_torch` as an empty namespace package.
    if "reeb_torch" not in sys.modules:
        sys.path.insert(0, str(REPO_ROOT))

from reeb_torch.eval import table3 as _table3  # noqa: E402
from reeb_torch.eval.table3 import (  # noqa: E402,F401 - re-exported for old imports
    IOUS,
    KS,
    METHODS,
    PAPER_TABLE3,
    Method,
    format_table,
    run_method,
)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark (``argv`` as on the command line) and return the JSON record."""
    return _table3.main(argv, prog="benchmarks/table3.py", default_data=default_dev_dirs())


if __name__ == "__main__":
    main()
