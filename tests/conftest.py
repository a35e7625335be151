"""Shared fixtures: the bundled sample frame and the dev data (skipped when absent).

The dev data is a folder holding ``kitti/`` (KITTI object frames: ``images/``, ``labels/``,
``calib/``), ``kitti_tracking/`` (the same layout) and ``bing_model/``: ``$REEB_DATA`` where
it is set, else ``../shared/data`` beside the repository. Tests that need a part of it that
is absent are skipped.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "data" / "kitti_000001.png"
DATA_ENV = "REEB_DATA"
DATA = Path(os.path.expanduser(os.environ.get(DATA_ENV) or REPO.parent / "shared" / "data"))
"""The dev data folder (module doc)."""
KITTI_DIR = DATA / "kitti"


@pytest.fixture(scope="session")
def sample_image() -> torch.Tensor:
    from reeb_torch.io import read_image

    return read_image(SAMPLE)


@pytest.fixture(scope="session")
def kitti_dir() -> Path:
    if not (KITTI_DIR / "images").is_dir():
        pytest.skip(f"{KITTI_DIR} is absent (set ${DATA_ENV} to the folder holding kitti/)")
    return KITTI_DIR


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


# -- a tiny detector on the bundled frames (the 'detect' extra): shared by its test modules --------

@pytest.fixture(scope="session")
def tiny_kitti(tmp_path_factory) -> Path:
    """The two bundled frames as a KITTI-format folder (images/, labels/, calib/)."""
    from tests.eval.test_eval import _example_kitti

    return _example_kitti(tmp_path_factory.mktemp("det") / "kitti")


@pytest.fixture(scope="session")
def detector_cache(tmp_path_factory) -> Path:
    """A feature and proposal cache folder the tiny detectors' fits share."""
    return tmp_path_factory.mktemp("cache")
