"""Compatibility: the recall metrics live in :mod:`reeb_torch.eval.metrics`.

``from reeb_torch.metrics import recall_table, compare_recall, recall_interval`` (the form
earlier READMEs and the detection example used) keeps working; new code imports
:mod:`reeb_torch.eval.metrics`.
"""

from .eval.metrics import *  # noqa: F401,F403
from .eval.metrics import __all__  # noqa: F401
