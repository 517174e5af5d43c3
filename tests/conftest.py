"""Shared fixtures. Real KITTI data is read from ../shared/data/kitti and skipped with a reason when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
KITTI_ROOT = REPO.parent / "shared" / "data" / "kitti"


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """Root of the shared real KITTI frames (odometry layout: sequences/04, poses/)."""
    if not (KITTI_ROOT / "sequences" / "04" / "calib.txt").is_file():
        pytest.skip(f"real KITTI frames not found at {KITTI_ROOT} (see ../shared/data/README.md)")
    return KITTI_ROOT
