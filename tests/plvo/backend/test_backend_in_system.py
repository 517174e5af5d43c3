"""The back end inside the whole System: it must make the trajectory better, and a bad registration must
get a small zeta and leave the trajectory where a good one puts it.

One short synthetic town sequence (seed 0, 10 m/s) is run eight times with inline workers (deterministic):
odometry alone, the full system, the system without the scale correction module (Ours (#)), and with keyframe-to-
keyframe NDT (`backend.lidar_target = "keyframe"`) the full system, the full system with one registration
corrupted (the NDT result moved 0.5 m and 1 deg, inside the jump gate, so it is accepted as converged), and the
same corruption with the paper's printed zeta formula as a control (it gives the bad registration a large weight,
and the trajectory follows it: the corruption is strong enough for the test to fail), these with zeta alone
weighing the edges; and the paper's formula again with the residual weight of the defaults. Features and depth priors
do not depend on the back end, so they are computed once and reused by the later runs.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from plvo.config import SystemConfig, merge, with_ablation
from plvo.geometry import se3
from plvo.results import MetricsResult

pytestmark = pytest.mark.slow

FRAMES, SEED = 40, 0
CORRUPT_CALL = 4  # the 4th registration (keyframes 4 -> 3) is corrupted
CORRUPTION = np.r_[0.5, 0.0, 0.0, 0.0, 0.0, np.radians(1.0)]  # lidar frame: 0.5 m forward, 1 deg yaw


class _Zetas:
    """Recorder keeping the back end's zeta per keyframe frame."""

    def __init__(self) -> None:
        self.zeta: dict[int, float] = {}

    def on_run_start(self, info) -> None:
        pass

    def on_frame(self, frame) -> None:
        pass

    def on_stage(self, frame_index: int, result) -> None:
        if isinstance(result, MetricsResult) and "zeta" in result.values:
            self.zeta[frame_index] = float(result.values["zeta"])

    def close(self) -> None:
        pass


def _memoise(monkeypatch) -> None:
    """Cache feature extraction and depth priors by frame content across the runs of this module."""
    import plvo.depth.extract as depth_mod
    import plvo.features.extract as feat_mod

    feats_cache: dict = {}
    depth_cache: dict = {}
    extract_features, extract_depth = feat_mod.extract_features, depth_mod.extract_depth

    def features(image, *args, **kwargs):
        key = (hashlib.sha1(np.ascontiguousarray(image)).hexdigest(), repr(kwargs))
        if key not in feats_cache:
            feats_cache[key] = extract_features(image, *args, **kwargs)
        return feats_cache[key]

    def depth(scan, feats, *args, **kwargs):
        key = (hashlib.sha1(np.ascontiguousarray(scan)).hexdigest(), id(feats))
        if key not in depth_cache:
            depth_cache[key] = extract_depth(scan, feats, *args, **kwargs)
        return depth_cache[key]

    monkeypatch.setattr(feat_mod, "extract_features", features)
    monkeypatch.setattr(depth_mod, "extract_depth", depth)


@pytest.fixture(scope="module")
def runs(synth_sequence_factory):
    from plvo.data.kitti import KittiOdometry
    from plvo.lidar import registration
    from plvo.runtime.run import run_dataset

    ds = KittiOdometry(synth_sequence_factory(FRAMES, seed=SEED), "00")
    base = merge(SystemConfig(), {"backend": {"concurrent": False}, "loop": {"enabled": False}})
    out = {"gt": ds.gt_T_world_cam}
    with pytest.MonkeyPatch.context() as mp:
        _memoise(mp)
        out["odometry"] = run_dataset(ds, merge(base, {"backend": {"enabled": False}})).poses
        rec = _Zetas()
        out["full"] = run_dataset(ds, base, rec).poses
        out["full_zeta"] = rec.zeta
        rec = _Zetas()
        out["no_module"] = run_dataset(ds, with_ablation(base, "no_scale_correction"), rec).poses
        out["no_module_zeta"] = rec.zeta
        # zeta alone weighs the edges here (no residual weight), as the paper has it
        ndt = merge(base, {"backend": {"lidar_target": "keyframe", "relative_pose_residual_power": 0.0,
                                       "relative_rotation_residual_power": 0.0}})
        rec = _Zetas()
        out["full_ndt"] = run_dataset(ds, ndt, rec).poses
        out["full_ndt_zeta"] = rec.zeta
        # the residual weight at the translation's power for both: the rotation's default power (1) is gentler and
        # leaves a corrupted rotation to zeta (the first check below, at the default formula)
        power = base.backend.relative_pose_residual_power
        weighted = merge(ndt, {"backend": {"relative_pose_residual_power": power,
                                           "relative_rotation_residual_power": power}})
        out["full_ndt_weighted"] = run_dataset(ds, weighted, _Zetas()).poses
        run = registration._run
        for formula, name, start in (("inverse", "inverse", ndt), ("paper", "paper", ndt),
                                     ("paper", "paper_weighted", weighted)):
            calls = {"n": 0}

            def corrupted(method, src, dst, init, cfg, calls=calls):
                T, fitness = run(method, src, dst, init, cfg)
                calls["n"] += 1
                return (T @ se3.exp(CORRUPTION) if calls["n"] == CORRUPT_CALL else T), fitness

            mp.setattr(registration, "_run", corrupted)
            rec = _Zetas()
            cfg = merge(start, {"registration": {"zeta_formula": formula}})
            out[f"corrupt_{name}"] = run_dataset(ds, cfg, rec).poses
            out[f"corrupt_{name}_zeta"] = rec.zeta
            mp.setattr(registration, "_run", run)
    return out


def _rel_err(gt: np.ndarray, est: np.ndarray, stride: int) -> float:
    """Mean translation error (m) of the relative poses `stride` frames apart."""
    e = [np.linalg.norm((se3.inv(se3.inv(gt[i]) @ gt[i + stride]) @ se3.inv(est[i]) @ est[i + stride])[:3, 3])
         for i in range(len(gt) - stride)]
    return float(np.mean(e))


def test_back_end_beats_odometry_alone(runs):
    """Relative-pose errors 3, 10 and 20 frames (3, 10, 20 m) apart. Measured: odometry 19.6 / 38.6 / 65.5 mm, full
    14.9 / 23.7 / 40.1 mm (13.8 / 21.2 / 36.6 with a 95x looser relative-rotation sigma, which drifts over a kilometre;
    16.4 / 22.4 / 39.7 without projecting the map's keyframe poses onto SE(3)); the registration
    fixes the drift the tracker accumulates over keyframes."""
    gt = runs["gt"]
    for stride, margin in ((3, 1.0), (10, 0.75), (20, 0.75)):
        odo, full = _rel_err(gt, runs["odometry"], stride), _rel_err(gt, runs["full"], stride)
        assert full < margin * odo, (stride, odo, full)


def test_scale_correction_module_matters(runs):
    """The paper's Ours (#): without the registration (no scale correction, no relative-pose factors) the bundle
    adjustment has only the depth priors to hold the scale. Relative-pose errors 3 / 10 / 20 frames apart, measured:
    full 14.9 / 23.7 / 40.1 mm, without the module 22.5 / 47.0 / 90.1 mm (worse than odometry alone: the 0.1 px
    point factors then pull the keyframes to the depth priors' scale, which is ~1 % off)."""
    assert runs["no_module_zeta"] == {}  # nothing was registered
    gt = runs["gt"]
    errs = {s: (_rel_err(gt, runs["full"], s), _rel_err(gt, runs["no_module"], s)) for s in (3, 10, 20)}
    for stride, margin in ((10, 0.75), (20, 0.75)):
        assert errs[stride][0] < margin * errs[stride][1], errs


def test_corrupted_registration_gets_small_zeta_and_does_not_pull(runs):
    zeta = runs["corrupt_inverse_zeta"]
    frames = sorted(zeta)
    bad_frame = frames[CORRUPT_CALL - 1]
    assert zeta[bad_frame] < 0.01, zeta
    good = [runs["full_ndt_zeta"][f] for f in frames if f != bad_frame]
    assert np.median(good) > 0.1, good  # an agreeing registration keeps about exp(-2) or more
    full, bad = runs["full_ndt"], runs["corrupt_inverse"]
    drift = np.linalg.norm(full[:, :3, 3] - bad[:, :3, 3], axis=1).max()
    assert drift < 0.05, drift  # the corruption is 0.5 m
    # control: the paper's printed formula trusts the corrupted registration and the trajectory follows it
    assert runs["corrupt_paper_zeta"][bad_frame] > 0.3
    pulled = np.linalg.norm(full[:, :3, 3] - runs["corrupt_paper"][:, :3, 3], axis=1).max()
    assert pulled > 0.2, pulled
    # the residual weight (backend.relative_pose_residual_power, and the rotation's at the same power) also sees the
    # corrupted alignment, whose residual grows, and keeps it from pulling even under the paper's formula
    held = np.linalg.norm(runs["full_ndt_weighted"][:, :3, 3] - runs["corrupt_paper_weighted"][:, :3, 3], axis=1)
    assert held.max() < 0.05, held.max()
