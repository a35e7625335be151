"""Compatibility: the Ray engine lives in :mod:`reeb_torch.runs.distributed`.

``from reeb_torch.distributed import propose_dataset, write_results`` (the README's form)
keeps working; new code imports :mod:`reeb_torch.runs.distributed`.
"""

from .runs.distributed import *  # noqa: F401,F403
from .runs.distributed import __all__  # noqa: F401
