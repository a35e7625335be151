"""Shared fixtures: the bundled sample frame and the shared KITTI folder (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "data" / "kitti_000001.png"
KITTI_DIR = REPO.parent / "shared" / "data" / "kitti"


@pytest.fixture(scope="session")
def sample_image() -> torch.Tensor:
    from reeb_torch.io import read_image

    return read_image(SAMPLE)


@pytest.fixture(scope="session")
def kitti_dir() -> Path:
    if not (KITTI_DIR / "images").is_dir():
        pytest.skip(f"{KITTI_DIR} is absent (the shared KITTI frames live beside the repository)")
    return KITTI_DIR


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)
