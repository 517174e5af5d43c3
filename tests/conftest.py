"""Shared fixtures. Real KITTI data is read from ../shared/data/kitti and skipped with a reason when absent."""

from __future__ import annotations

import os

# As the CLI does (plvo_app/cli.py): multi-threaded BLAS on small matrices costs 2-3x the CPU on 2 cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
# The tests mirror the packages (tests/plvo/tracking/test_frontend.py tests plvo/tracking/frontend.py) and are
# imported by path (pyproject: --import-mode=importlib: a folder tests/plvo must not stand in for the package plvo);
# what several of them share (fakes, scenes, the faults table) is imported by name from tests/helpers.
sys.path.insert(0, str(REPO / "tests" / "helpers"))
KITTI_ROOT = REPO.parent / "shared" / "data" / "kitti"

# What the suite writes to its temporary folder (synthetic towns, twins, recordings) at its peak, kept until the
# session ends (1722 MB measured over the whole suite at e9f15a5): with less free, a full disk shows as OSErrors in
# whichever fixture happens to write next, ten minutes in, so the session stops at once and says why.
SUITE_TMP_MB = 1800


def _tmp_space() -> tuple[Path, int]:
    tmp = Path(os.environ.get("PYTEST_DEBUG_TEMPROOT") or tempfile.gettempdir())
    return tmp, shutil.disk_usage(tmp).free // 2**20


def pytest_report_header(config) -> str:
    tmp, free_mb = _tmp_space()
    return f"temporary files: {tmp}, {free_mb} MB free (the suite writes about {SUITE_TMP_MB} MB)"


def pytest_sessionstart(session) -> None:
    tmp, free_mb = _tmp_space()
    if free_mb < SUITE_TMP_MB and not session.config.getoption("collectonly"):
        pytest.exit(f"{tmp} has {free_mb} MB free and the suite writes up to {SUITE_TMP_MB} MB there: free some space "
                    "or point TMPDIR at a disk with room", returncode=pytest.ExitCode.USAGE_ERROR)


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """Root of the shared real KITTI frames (odometry layout: sequences/04, poses/)."""
    if not (KITTI_ROOT / "sequences" / "04" / "calib.txt").is_file():
        pytest.skip(f"real KITTI frames not found at {KITTI_ROOT} (see ../shared/data/README.md)")
    return KITTI_ROOT


# --- synthetic town (plvo_synth) -------------------------------------------------------------------------

SYNTH_SEQ_FRAMES = 20


@pytest.fixture(scope="session")
def synth_sequence_factory(tmp_path_factory):
    """Callable (n_frames, seed=0, **generate_sequence kwargs) -> root of a synthetic sequence '00' in the KITTI
    layout, generated once per session for each distinct set of arguments (e.g. a longer or a loop sequence)."""
    from plvo_synth import generate_sequence

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


# --- KITTI twins (plvo_synth.twin) -----------------------------------------------------------------------

TWIN_FRAMES = "60:80"  # 16 m at 8 m/s (07 starts standing)
TWIN_SEQUENCE = "07"


@pytest.fixture(scope="session")
def twin_root(kitti_root, tmp_path_factory) -> Path:
    """Root of a 20-frame KITTI twin of 07 (frames 60:80, 8 movers, depth written); generated once per session."""
    from plvo_synth.twin.generate import TwinSettings, generate_twin

    root = tmp_path_factory.mktemp("twin07")
    settings = TwinSettings(str(kitti_root / "poses" / f"{TWIN_SEQUENCE}.txt"), TWIN_FRAMES, seed=0, traffic=8,
                            write_depth=True)
    return generate_twin(root, TWIN_SEQUENCE, settings)


@pytest.fixture(scope="session")
def ideal_twin_root(kitti_root, tmp_path_factory) -> Path:
    """The same twin with ideal sensors (plvo synth --ideal): raw sweeps, each return at its own time, and no sensor
    imperfections, for the tests of deskewing against the surfaces' truth."""
    from plvo_synth.twin.generate import TwinSettings, generate_twin
    from plvo_synth.twin.realism import IDEAL

    root = tmp_path_factory.mktemp("twin07_ideal")
    settings = TwinSettings(str(kitti_root / "poses" / f"{TWIN_SEQUENCE}.txt"), TWIN_FRAMES, seed=0, traffic=8,
                            write_depth=True, realism=IDEAL)
    return generate_twin(root, TWIN_SEQUENCE, settings)


# --- an out-and-back twin: a street driven, turned on, and driven back (lidar loops in the opposite direction) -----

OUTBACK_SEQUENCE = "00"


def _out_and_back_poses(leg_m: float = 50.0, back_m: float = 70.0, radius_m: float = 6.0, lanes_m: float = 3.5,
                        v_leg: float = 12.0, v_turn: float = 8.0, ramp_m: float = 8.0) -> np.ndarray:
    """(N,4,4) KITTI cam0 poses (x right, y down, z forward; frame 0 the origin), 10 Hz: leg_m straight ahead at
    v_leg, a turning loop (right arc a, left arc pi + 2a, right arc a, all of radius_m) at v_turn that ends lanes_m
    to the left heading back, and back_m back (past the start)."""

    def advance(p: np.ndarray, h: float, prim: tuple) -> tuple[np.ndarray, float]:
        if prim[0] == "line":
            return p + prim[1] * np.array([np.cos(h), np.sin(h)]), h
        _, r, ang = prim
        sg = np.sign(ang)
        c = p + r * sg * np.array([-np.sin(h), np.cos(h)])
        h2 = h + ang
        return c + r * sg * np.array([np.sin(h2), -np.cos(h2)]), h2

    def walk(prims: list, s: float | None = None) -> tuple[np.ndarray, float]:
        """Position (x right, y forward) and heading at arc length s (the end when None)."""
        p, h = np.zeros(2), np.pi / 2
        for prim in prims:
            length = prim[1] if prim[0] == "line" else prim[1] * abs(prim[2])
            if s is not None and s <= length:
                part = ("line", s) if prim[0] == "line" else ("arc", prim[1], np.sign(prim[2]) * s / prim[1])
                return advance(p, h, part)
            p, h = advance(p, h, prim)
            if s is not None:
                s -= length
        return p, h

    def turn(a: float) -> list:
        return [("arc", radius_m, -a), ("arc", radius_m, np.pi + 2 * a), ("arc", radius_m, -a)]

    lo, hi = 0.0, 1.5
    for _ in range(60):  # the swing a that ends the turn lanes_m to the left
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if -walk(turn(mid))[0][0] < lanes_m else (mid, hi)
    prims = [("line", leg_m), *turn(0.5 * (lo + hi)), ("line", back_m)]
    total = leg_m + back_m + radius_m * (np.pi + 4 * 0.5 * (lo + hi))

    def speed(s: float) -> float:
        away = max(leg_m - s, s - (total - back_m), 0.0)  # metres from the turn
        return v_turn + min(away / ramp_m, 1.0) * (v_leg - v_turn)

    arc, s = [], 0.0
    while s <= total:
        arc.append(s)
        for _ in range(100):
            s += speed(s) * 1e-3
    poses = []
    for s in arc:
        (x, y), h = walk(prims, s)
        forward = np.array([np.cos(h), 0.0, np.sin(h)])
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = np.cross([0.0, 1.0, 0.0], forward), [0.0, 1.0, 0.0], forward
        T[:3, 3] = [x, 0.0, y]
        poses.append(T)
    return np.array(poses)


@pytest.fixture(scope="session")
def outback_twin(tmp_path_factory) -> Path:
    """Root of a twin (sequence '00', no traffic) driven out 50 m along a city street at 12 m/s, turned on a 6 m
    loop at 8 m/s and driven back 3.5 m to the left, 20 m past the start: 153 frames, the return seeing each place
    from the other side 90-140 frames later (more than loop.min_keyframe_gap keyframes), and the last 20 m there
    for the place nodes of the way back (lidar_place_reach_m). Generated once per session (~1-1.5 min)."""
    from plvo_synth.twin.generate import TwinSettings, generate_twin
    from plvo_synth.twin.realism import IDEAL

    root = tmp_path_factory.mktemp("outback")
    poses = _out_and_back_poses()
    follow = root / "outback_poses.txt"
    np.savetxt(follow, poses[:, :3].reshape(-1, 12), fmt="%.9e")
    # ideal sensors: the place-recognition tests read its raw sweeps and deskew them with the truth, and measure
    # registrations against the truth to the centimetre
    return generate_twin(root / "twin", OUTBACK_SEQUENCE, TwinSettings(str(follow), None, seed=0, traffic=0,
                                                                      realism=IDEAL))
