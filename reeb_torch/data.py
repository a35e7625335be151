"""Compatibility: the KITTI reader lives in :mod:`reeb_torch.eval.data`.

``from reeb_torch.data import KittiDataset, read_kitti_labels`` (the form earlier READMEs and
the detection example used) keeps working; new code imports :mod:`reeb_torch.eval.data`.
"""

from .eval.data import *  # noqa: F401,F403
from .eval.data import __all__  # noqa: F401
