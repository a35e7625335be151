"""Compatibility: the ``reeb`` command lives in :mod:`reeb_torch.runs.cli`.

Kept for console scripts installed before the move (they run ``reeb_torch.cli:main``) and
for ``python -m reeb_torch.cli``; reinstalling (``pip install -e .``) points ``reeb`` at
:mod:`reeb_torch.runs.cli`.
"""

from .runs.cli import main

__all__ = ["main"]

if __name__ == "__main__":
    main()
