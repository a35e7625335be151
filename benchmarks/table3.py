"""The paper's Table 3 on KITTI-format folders: recall of REEB and of the classical baselines.

The ``reeb eval`` command (:mod:`reeb_torch.eval.command`) with the project's defaults:
``--data`` is the two dev folders beside the repository, ``../shared/data/kitti`` and
``../shared/data/kitti_tracking`` (every table is given for each folder and for both
together), and ``--bing-model`` is ``../shared/data/bing_model``. See
:mod:`reeb_torch.eval.methods` for the rows, :mod:`reeb_torch.eval.report` for the tables
(all objects - the headline -, KITTI-moderate objects, class mean, per-class recall at
2000 / IoU 0.7, AR) and the files written into ``--out`` (default ``runs/table3``):
``table3.txt``, ``table3.csv``, ``table3.json`` and two plots.

Rerun: ``python benchmarks/table3.py [--data DIR ...] [--limit N] [--frames A:B ...]
[--methods M,...] [--cross-validate FOLDS [--whole-drives]] [--leave-folder-out]`` (the
default's table: ``--methods reeb-training-free,reeb-default --cross-validate 10 --whole-drives
--leave-folder-out --batch 0 --out docs/results/table3_default``; its whole-drives row is the
estimate to read first); ``--data``,
``--frames`` and ``--methods`` repeat (``--frames 0:39 --frames 40:59``) or take
comma-separated values (``--frames 0:39,40:59``). ``--frames`` selects numeric ids (KITTI
object frames; select tracking frames by folder). ``--help`` lists every option.
From code, ``main(argv)`` returns the JSON record.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Sequence

try:  # imported as benchmarks.table3
    from ._common import REPO_ROOT, data_root, default_dev_dirs
except ImportError:  # run as a script, or loaded from its file
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import REPO_ROOT, data_root, default_dev_dirs  # type: ignore[no-redef]

    # The checkout's package first: run from benchmarks/, an editable install made before
    # reeb_torch/__init__.py existed resolves `reeb_torch` as an empty namespace package.
    if "reeb_torch" not in sys.modules:
        sys.path.insert(0, str(REPO_ROOT))

from reeb_torch.eval.command import table3_command  # noqa: E402

PROG = "benchmarks/table3.py"
BING_MODEL = data_root() / "bing_model"
"""BING's model files in the dev data (``$REEB_DATA``; ``--bing-model``'s default)."""

command = table3_command(PROG, data_default=default_dev_dirs(), bing_default=BING_MODEL)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark (``argv`` as on the command line) and return the JSON record; a bad
    option or unusable data raises :class:`click.ClickException` (exit code 2 from a shell)."""
    return command.main(args=list(argv) if argv is not None else None, prog_name=PROG, standalone_mode=False)


if __name__ == "__main__":
    command.main(prog_name=PROG)
