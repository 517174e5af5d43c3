"""Shared fixtures. Real KITTI data is read from ../shared/data/kitti and skipped with a reason when absent."""

from __future__ import annotations

import os

# As the CLI does (plvo_app/cli.py): multi-threaded BLAS on small matrices costs 2-3x the CPU on 2 cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

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


# --- synthetic town (plvo.data.synth) -------------------------------------------------------------------------

SYNTH_SEQ_FRAMES = 20


@pytest.fixture(scope="session")
def synth_sequence_factory(tmp_path_factory):
    """Callable (n_frames, seed=0, **generate_sequence kwargs) -> root of a synthetic sequence '00' in the KITTI
    layout, generated once per session for each distinct set of arguments (e.g. a longer or a loop sequence)."""
    from plvo.data.synth import generate_sequence

    made: dict[tuple, Path] = {}

    def make(n_frames: int, seed: int = 0, **kwargs) -> Path:
        key = (n_frames, seed, tuple(sorted(kwargs.items())))
        if key not in made:
            root = tmp_path_factory.mktemp(f"synth_{n_frames}f_seed{seed}")
            made[key] = generate_sequence(root, "00", n_frames=n_frames, seed=seed, **kwargs)
        return made[key]

    return make


@pytest.fixture(scope="session")
def synth_seq(synth_sequence_factory) -> Path:
    """Root (KITTI odometry layout, sequence '00') of a 20-frame synthetic town sequence at 10 m/s, seed 0, with
    per-pixel depth in sequences/00/gt/depth; generated once per session."""
    return synth_sequence_factory(SYNTH_SEQ_FRAMES, seed=0, write_depth=True)


# --- KITTI twins (plvo.data.synth.twin) -----------------------------------------------------------------------

TWIN_FRAMES = "60:80"  # 16 m at 8 m/s (07 starts standing)
TWIN_SEQUENCE = "07"


@pytest.fixture(scope="session")
def twin_root(kitti_root, tmp_path_factory) -> Path:
    """Root of a 20-frame KITTI twin of 07 (frames 60:80, 8 movers, depth written); generated once per session."""
    from plvo.data.synth.twin.generate import TwinSettings, generate_twin

    root = tmp_path_factory.mktemp("twin07")
    settings = TwinSettings(str(kitti_root / "poses" / f"{TWIN_SEQUENCE}.txt"), TWIN_FRAMES, seed=0, traffic=8,
                            write_depth=True)
    return generate_twin(root, TWIN_SEQUENCE, settings)
