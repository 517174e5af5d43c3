"""The valid range of every numeric config field, by dotted key, checked when a config is loaded or built.

Zero or negative counts, sizes and factors would be accepted silently or crash deep inside OpenCV or GTSAM; a
range is refused here with the dotted key, the value and the range. Every numeric field of `plvo.config` must have
an entry (tests/test_config_ranges.py checks it), so a new field comes with its range.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plvo.errors import ConfigError


@dataclass(frozen=True)
class Range:
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def __str__(self) -> str:
        if self.hi == math.inf:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


POSITIVE = Range(0.0, lo_open=True)  # sizes, distances, factors, sigmas: zero is meaningless
NON_NEGATIVE = Range(0.0)  # thresholds where 0 means "off"
COUNT = Range(1)  # counts and iterations: at least one
COUNT0 = Range(0)  # counts where 0 means "none"
SHARE = Range(0.0, 1.0)  # fractions
RATIO = Range(0.0, 1.0, lo_open=True)  # Lowe ratios and scales: (0, 1]
ANGLE = Range(0.0, 90.0, lo_open=True)  # angular tolerances between lines, degrees
HAMMING = Range(0, 256)  # 256-bit ORB / LBD descriptors
COSINE = Range(0.0, 1.0, hi_open=True)

RANGES: dict[str, Range] = {
    "orb.n_features": COUNT, "orb.scale_factor": Range(1.0, 2.0, lo_open=True), "orb.n_levels": Range(1, 16),
    "orb.fast_threshold": Range(1, 254), "orb.fast_threshold_min": Range(1, 254), "orb.grid_cell_px": COUNT,
    "orb.edge_threshold": COUNT,
    "lines.min_length_px": POSITIVE, "lines.chain_endpoint_px": NON_NEGATIVE, "lines.chain_angle_deg": ANGLE,
    "lines.chain_offset_px": NON_NEGATIVE, "lines.merge_distance_px": NON_NEGATIVE, "lines.merge_angle_deg": ANGLE,
    "lines.merge_overlap": SHARE, "lines.max_iterations": COUNT, "lines.lsd_scale": RATIO,
    "lines.max_lines": COUNT, "lines.raw_min_length_px": NON_NEGATIVE, "lines.min_anchor_px": NON_NEGATIVE,
    "matching.point_ratio": RATIO, "matching.point_max_hamming": HAMMING, "matching.point_window_px": POSITIVE,
    "matching.line_max_lbd": HAMMING, "matching.line_angle_deg": ANGLE, "matching.line_length_ratio": POSITIVE,
    "matching.line_midpoint_px": POSITIVE, "matching.line_midpoint_px_unpredicted": POSITIVE,
    "matching.line_ratio": RATIO,
    "depth.point_patch_px": COUNT, "depth.line_patch_px": COUNT, "depth.min_points": Range(3),
    "depth.depth_jump_ratio": NON_NEGATIVE, "depth.depth_jump_min_m": NON_NEGATIVE,
    "depth.plane_inlier_m": POSITIVE, "depth.plane_max_rms_m": POSITIVE, "depth.min_ray_plane_cos": COSINE,
    "depth.max_depth_m": POSITIVE, "depth.line_min_points": Range(2), "depth.line_max_rms_m": POSITIVE,
    "depth.line_lm_iterations": COUNT, "depth.line_reprojection_weight": NON_NEGATIVE,
    "depth.min_inlier_fraction": SHARE, "depth.plane_max_flatness": RATIO, "depth.grid_cell_px": COUNT,
    "depth.zbuffer_px": COUNT, "depth.min_depth_m": NON_NEGATIVE, "depth.line_max_points": Range(2),
    "depth.line_huber_m": POSITIVE, "depth.line_core_px": POSITIVE, "depth.line_inlier_m": POSITIVE,
    "depth.line_min_coverage": SHARE, "depth.line_max_reproj_px": POSITIVE, "depth.min_ray_line_sin": COSINE,
    "tracking.keyframe_every": COUNT, "tracking.keyframe_max_gap": COUNT, "tracking.min_tracked_landmarks": COUNT0,
    "tracking.max_rotation_deg": POSITIVE, "tracking.min_pnp_inliers": Range(4),
    "tracking.weak_inlier_share": SHARE, "tracking.rescue_yaw_deg": Range(-90.0, 90.0),
    "tracking.ransac_reproj_px": POSITIVE, "tracking.ransac_line_px": POSITIVE, "tracking.ransac_iterations": COUNT,
    "tracking.outlier_reproj_px": POSITIVE, "tracking.search_radius_px": POSITIVE,
    "tracking.search_keyframes": COUNT0, "tracking.line_search_px": POSITIVE, "tracking.line_search_angle_deg": ANGLE,
    "tracking.line_search_overlap": SHARE, "tracking.drop_unreachable_every": COUNT0,
    "crosscheck.voxel_m": POSITIVE, "crosscheck.min_range_m": NON_NEGATIVE, "crosscheck.max_range_m": POSITIVE,
    "crosscheck.min_fitness": SHARE, "crosscheck.degenerate_ratio": SHARE,
    "crosscheck.agree_m": POSITIVE, "crosscheck.agree_share": NON_NEGATIVE, "crosscheck.agree_deg": POSITIVE,
    "crosscheck.doubt_m": POSITIVE, "crosscheck.doubt_share": NON_NEGATIVE, "crosscheck.doubt_deg": POSITIVE,
    "crosscheck.frozen_image_grey": NON_NEGATIVE, "crosscheck.still_m": NON_NEGATIVE,
    "crosscheck.gap_factor": Range(1.0, lo_open=True), "crosscheck.time_offset_s": Range(-0.5, 0.5),
    "crosscheck.offset_max_s": Range(0.0, 0.5, lo_open=True), "crosscheck.offset_sigma_s": POSITIVE,
    "crosscheck.offset_warn_s": NON_NEGATIVE,
    "registration.voxel_m": POSITIVE, "registration.ndt_resolution_m": POSITIVE,
    "registration.max_iterations": COUNT, "registration.max_range_m": POSITIVE,
    "registration.max_correspondence_m": POSITIVE, "registration.min_range_m": NON_NEGATIVE,
    "registration.ndt_coarse_resolution_m": NON_NEGATIVE, "registration.min_fitness": SHARE,
    "registration.max_jump_m": POSITIVE, "registration.max_jump_deg": POSITIVE,
    "backend.window_keyframes": Range(2), "backend.sigma_point_px": POSITIVE, "backend.sigma_line": POSITIVE,
    "backend.sigma_relative_pose": POSITIVE, "backend.sigma_relative_rotation_deg": POSITIVE,
    "backend.relative_pose_residual_m": POSITIVE, "backend.relative_pose_residual_power": NON_NEGATIVE,
    "backend.relative_rotation_residual_power": NON_NEGATIVE,
    "backend.stereo_baseline_m": POSITIVE, "backend.huber_point": POSITIVE, "backend.huber_line": POSITIVE,
    "depth.reference_ring_spacing_px": POSITIVE, "depth.adapt_min_ratio": Range(1.0),
    "depth.adapt_max_ratio": Range(1.0),
    "backend.iterations": COUNT, "backend.outlier_px": NON_NEGATIVE, "backend.max_lag_frames": COUNT0,
    "backend.local_map_keyframes": COUNT, "backend.local_map_voxel_m": POSITIVE,
    "backend.local_map_source_points": Range(100),
    "backend.worker_timeout_s": POSITIVE,
    "loop.min_keyframe_gap": COUNT0, "loop.min_score": NON_NEGATIVE, "loop.consistency": COUNT,
    "loop.min_inliers": Range(4), "loop.min_neighbour_score": NON_NEGATIVE, "loop.neighbours": COUNT,
    "loop.island_gap": COUNT0, "loop.max_verify": COUNT, "loop.loop_cooldown": COUNT0, "loop.ratio": RATIO,
    "loop.point_max_hamming": HAMMING, "loop.line_max_hamming": HAMMING, "loop.ransac_px": POSITIVE,
    "loop.min_off_plane": COUNT0, "loop.plane_tolerance_m": POSITIVE, "loop.odom_sigma_rot": POSITIVE,
    "loop.odom_sigma_trans": POSITIVE, "loop.loop_sigma_rot": POSITIVE, "loop.loop_sigma_trans": POSITIVE,
    "loop.pgo_iterations": COUNT, "loop.global_ba_iterations": COUNT, "loop.global_ba_max_px": POSITIVE,
    "loop.global_ba_max_points": COUNT0,
    "loop.global_ba_max_move_m": NON_NEGATIVE, "loop.global_ba_move_fraction": NON_NEGATIVE,
    "loop.max_drift_fraction": NON_NEGATIVE, "loop.max_drift_floor_m": NON_NEGATIVE,
    "loop.max_view_m": POSITIVE,
    "loop.lidar_place_spacing_m": NON_NEGATIVE, "loop.lidar_place_reach_m": NON_NEGATIVE,
    "loop.lidar_place_radius_m": POSITIVE, "loop.lidar_place_voxel_m": POSITIVE, "loop.lidar_place_hamming": HAMMING,
    "loop.lidar_place_min_inliers": Range(3), "loop.scan_verify_radius_m": POSITIVE, "loop.scan_min_overlap": SHARE,
    "loop.scan_max_error_m": POSITIVE, "loop.scan_min_constraint": NON_NEGATIVE, "loop.scan_basin_m": NON_NEGATIVE,
    "loop.scan_unique_m": POSITIVE, "loop.scan_max_edge_m": POSITIVE,
    "loop.max_lag_frames": COUNT0, "loop.global_ba_lag_frames": COUNT0,
}

# Pairs that must be ordered: (smaller key, larger key).
ORDERED: tuple[tuple[str, str], ...] = (
    ("orb.fast_threshold_min", "orb.fast_threshold"),
    ("tracking.keyframe_every", "tracking.keyframe_max_gap"),
    ("registration.min_range_m", "registration.max_range_m"),
    ("crosscheck.min_range_m", "crosscheck.max_range_m"),
    ("depth.min_depth_m", "depth.max_depth_m"),
    ("depth.adapt_min_ratio", "depth.adapt_max_ratio"),
)


def choices_of(hint: Any) -> tuple[str, ...]:
    """The values a choice field takes (its type a Literal, or a union of Literals: the choices stand beside the
    field in plvo.config); () for any other type."""
    if typing.get_origin(hint) is typing.Literal:
        return tuple(typing.get_args(hint))
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        parts = [choices_of(a) for a in typing.get_args(hint)]
        return tuple(v for p in parts for v in p) if all(parts) else ()
    return ()


def choice_fields(cfg: Any) -> dict[str, tuple[tuple[str, ...], Any]]:
    """Dotted key -> (its choices, its value) of every choice field of a (nested) config dataclass. Checked when
    a file is read, also those used only off the defaults' path (a typo there would otherwise pass until a run
    took that path)."""
    out: dict[str, tuple[tuple[str, ...], Any]] = {}
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            if choices_of(hints[f.name]):
                out[f"{section.name}.{f.name}"] = (choices_of(hints[f.name]), getattr(sub, f.name))
    return out


# Every numeric field is bounded above too: by its range, else by the cap of its unit (the key's suffix), else by
# the cap of its kind. A count of 1e12 features, a window of a million keyframes or a timeout of 1e30 s would pass
# a lower bound alone and exhaust the memory or wait for ever.
UNIT_CAPS: dict[str, float] = {"_m": 1e5, "_px": 1e5, "_deg": 360.0, "_s": 3600.0}
COUNT_CAP = 1e8  # int fields: counts, iterations, gaps
FACTOR_CAP = 1e6  # other float fields: factors, sigmas, weights, powers


def bounded(key: str, rng: Range, is_int: bool) -> Range:
    """`rng` with its upper bound capped (UNIT_CAPS by the key's suffix, else COUNT_CAP / FACTOR_CAP)."""
    cap = next((c for suffix, c in UNIT_CAPS.items() if key.endswith(suffix)), COUNT_CAP if is_int else FACTOR_CAP)
    return rng if rng.hi <= cap else dataclasses.replace(rng, hi=cap, hi_open=False)


def numeric_fields(cfg: Any) -> dict[str, Any]:
    """Dotted key -> value of every int, float or tuple-of-numbers field of a (nested) config dataclass."""
    out: dict[str, Any] = {}
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            want = hints[f.name]
            if want in (int, float) or typing.get_origin(want) is tuple:
                out[f"{section.name}.{f.name}"] = getattr(sub, f.name)
    return out


def check_ranges(cfg: Any) -> None:
    """Raise ConfigError naming the first dotted key whose value is out of its range (or has no range)."""
    values = numeric_fields(cfg)
    for key, value in values.items():
        if key not in RANGES:
            raise ConfigError(f"config key '{key}' has no valid range in plvo/config_ranges.py")
        items = value if isinstance(value, tuple) else (value,)
        rng = bounded(key, RANGES[key], all(isinstance(v, int) for v in items))
        for v in items:
            if not rng.contains(float(v)):
                raise ConfigError(f"config key '{key}' = {v!r} is out of range (must be {rng})")
    for key, (allowed, value) in choice_fields(cfg).items():
        if value not in allowed:
            raise ConfigError(f"config key '{key}' = {value!r} must be one of {', '.join(allowed)}")
    vocab = getattr(getattr(cfg, "loop", None), "vocab_dir", "")
    if vocab:  # read by the loop closer's process at its start: a wrong folder said here, not as a worker's failure
        missing = [n for n in ("orb.npz", "lbd.npz") if not (Path(vocab) / n).is_file()]
        if missing:
            raise ConfigError(f"config key 'loop.vocab_dir' = {vocab!r}: no {' or '.join(missing)} there "
                              "(plvo vocab --out writes them; empty: the shipped vocabularies)")
    for small, large in ORDERED:
        if values[small] > values[large]:
            raise ConfigError(f"config key '{small}' = {values[small]!r} must not exceed '{large}' = "
                              f"{values[large]!r}")
