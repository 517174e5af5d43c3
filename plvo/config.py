"""Configuration: nested frozen dataclasses, one per subsystem, with the paper's parameters as defaults.

Each numeric field declares its range and unit beside it (`setting(default, range, unit)`, plvo.config_fields), each
choice field its values as its type (a Literal). Load with `load_config(path)` (TOML; unknown keys, wrong types and
values out of their range or choices are refused by their dotted name), save with `save_config`. Degrees appear
only in fields whose name says so (`*_deg`).
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple, TypeVar

from plvo.atomic import write_text_atomic
from plvo.config_fields import (
    ANGLE,
    COSINE,
    COUNT,
    COUNT0,
    HAMMING,
    NON_NEGATIVE,
    POSITIVE,
    RATIO,
    SHARE,
    Range,
    check_ranges,
    choices_of,
    setting,
)
from plvo.errors import ConfigError

# A choice field's type is the Literal of its values: a file is checked against it when read (plvo.config_fields)
RegistrationMethod = Literal["ndt", "icp", "gicp"]  # plvo.lidar.registration's


@dataclass(frozen=True)
class OrbConfig:
    n_features: int = setting(1000, COUNT, "features")  # paper, III: 1000 ORB features an image
    scale_factor: float = setting(1.2, Range(1.0, 2.0, lo_open=True))
    # ORB-SLAM2's 8 but the coarsest: as accurate, and twin 08 keeps its last loop (docs/config.md#orb,
    # docs/results/faster_config/)
    n_levels: int = setting(7, Range(1, 16), "levels")
    fast_threshold: int = setting(20, Range(1, 254), "grey levels")  # ORB-SLAM2's iniThFAST
    # ORB-SLAM2's minThFAST, retried in cells that found nothing
    fast_threshold_min: int = setting(7, Range(1, 254), "grey levels")
    # bucketing cell size for even spread (ORB-SLAM2 uses 30 px at level 0)
    grid_cell_px: int = setting(35, COUNT, "px")
    edge_threshold: int = setting(19, COUNT, "px")


@dataclass(frozen=True)
class LineConfig:
    min_length_px: float = setting(50.0, POSITIVE, "px")  # paper, III: segments under 50 px are discarded
    # The repair's distances (px) hold for lsd_scale 0.5 and finer; below it they grow by 0.5 / lsd_scale.
    chain_endpoint_px: float = setting(10.0, NON_NEGATIVE, "px")  # endpoints this close may be chained
    chain_angle_deg: float = setting(3.0, ANGLE, "deg")  # chained segments must be this collinear
    chain_offset_px: float = setting(1.5, NON_NEGATIVE, "px")  # and lie this close to each other's supporting line
    # near-parallel segments this close are merged (double edges)
    merge_distance_px: float = setting(3.0, NON_NEGATIVE, "px")
    merge_angle_deg: float = setting(3.0, ANGLE, "deg")
    merge_overlap: float = setting(0.5, SHARE)  # fraction of the shorter segment that must overlap the longer
    # repeat chaining and merging until stable, at most this often
    max_iterations: int = setting(10, COUNT, "iterations")
    # LSD on the image downsampled to 0.35: two thirds of its CPU at 0.5, the development set's accuracy kept
    # (docs/config.md#lines, docs/results/faster_config/)
    lsd_scale: float = setting(0.35, RATIO)
    max_lines: int = setting(300, COUNT, "segments")  # keep the longest segments when more are found
    lsd_refine: bool = True  # OpenCV's LSD_REFINE_STD (else LSD_REFINE_NONE)
    # raw LSD segments shorter than this take no part in the repair
    raw_min_length_px: float = setting(8.0, NON_NEGATIVE, "px")
    # a repaired segment's longest raw member must be at least this long
    min_anchor_px: float = setting(0.0, NON_NEGATIVE, "px")
    in_thread: bool = True  # run LSD + repair + LBD in a worker thread beside ORB


@dataclass(frozen=True)
class MatchingConfig:
    point_ratio: float = setting(0.8, RATIO)  # Lowe ratio for ORB Hamming matches
    point_max_hamming: int = setting(64, HAMMING, "bits")
    point_mutual: bool = True
    # search radius around the predicted position, when a prediction exists
    point_window_px: float = setting(60.0, POSITIVE, "px")
    line_max_lbd: int = setting(80, HAMMING, "bits")  # LBD Hamming distance bound
    line_angle_deg: float = setting(2.0, ANGLE, "deg")  # paper, III: angle threshold 2 deg
    line_length_ratio: float = setting(0.1, POSITIVE)  # paper, III: length difference ratio 0.1
    # paper, III: midpoint distance 5 px (after the predicted motion)
    line_midpoint_px: float = setting(5.0, POSITIVE, "px")
    line_midpoint_px_unpredicted: float = setting(40.0, POSITIVE, "px")  # window when no motion prediction is available
    # Lowe ratio among a line's geometric candidates (1.0: off, as in the paper)
    line_ratio: float = setting(1.0, RATIO)


@dataclass(frozen=True)
class DepthConfig:
    point_patch_px: int = setting(7, COUNT, "px")  # half-size of the square patch searched around a point feature
    line_patch_px: int = setting(4, COUNT, "px")  # half-width of the band searched around a line feature
    min_points: int = setting(4, Range(3), "points")  # fewer lidar points in a patch: no prior
    # depth discontinuity between foreground and background, relative
    depth_jump_ratio: float = setting(0.05, NON_NEGATIVE)
    depth_jump_min_m: float = setting(0.3, NON_NEGATIVE, "m")
    plane_inlier_m: float = setting(0.08, POSITIVE, "m")
    plane_max_rms_m: float = setting(0.1, POSITIVE, "m")
    min_ray_plane_cos: float = setting(0.1, COSINE)  # rays closer to parallel with the plane give no depth
    max_depth_m: float = setting(80.0, POSITIVE, "m")
    line_min_points: int = setting(6, Range(2), "points")
    line_max_rms_m: float = setting(0.15, POSITIVE, "m")
    line_lm_iterations: int = setting(10, COUNT, "iterations")
    # metres a pixel of reprojection error weighs against point distances
    line_reprojection_weight: float = setting(0.1, NON_NEGATIVE, "m/px")
    min_inlier_fraction: float = setting(0.6, SHARE)  # plane inliers must be this share of the segmented foreground
    # sqrt(eig1/eig2) above this: tilt unknown, plane facing the camera
    plane_max_flatness: float = setting(0.35, RATIO)
    grid_cell_px: int = setting(8, COUNT, "px")  # cell size of the projected-scan index
    zbuffer_px: int = setting(1, COUNT, "px")  # z-buffer block size: the nearest return of each block is kept
    min_depth_m: float = setting(0.5, NON_NEGATIVE, "m")  # projected returns nearer than this are dropped
    # band points kept a segment (evenly thinned), bounds the LM's cost
    line_max_points: int = setting(64, Range(2), "points")
    # Huber threshold on point-to-line distances (near the paper's sum of distances)
    line_huber_m: float = setting(0.02, POSITIVE, "m")
    # band points this close to the segment set each stretch's reference depth
    line_core_px: float = setting(2.0, POSITIVE, "px")
    line_inlier_m: float = setting(0.2, POSITIVE, "m")  # band points farther from the fitted line are not counted
    line_min_coverage: float = setting(0.3, SHARE)  # inliers must span this fraction of the segment
    # fitted line's RMS reprojection residual against the segment
    line_max_reproj_px: float = setting(2.0, POSITIVE, "px")
    min_ray_line_sin: float = setting(0.05, COSINE)  # end rays closer to parallel with the 3D line give no endpoints
    # sparser lidars (plvo.depth.density): patches scaled by the scan's ring spacing over the HDL-64E's in KITTI's
    # camera when it is at least adapt_min_ratio times larger (16 beams: about 4x, 32: 2x; 64: unchanged)
    adapt_to_ring_spacing: bool = True
    reference_ring_spacing_px: float = setting(5.0, POSITIVE, "px")
    adapt_min_ratio: float = setting(1.5, Range(1.0))
    adapt_max_ratio: float = setting(5.0, Range(1.0))


@dataclass(frozen=True)
class TrackingConfig:
    points_only: bool = False  # the paper's point-only baseline
    use_depth_priors: bool = True  # ablation "no depth priors": landmarks by triangulation only
    keyframe_every: int = setting(3, COUNT, "frames")  # paper: a keyframe every 3-4 frames
    keyframe_max_gap: int = setting(4, COUNT, "frames")
    min_tracked_landmarks: int = setting(60, COUNT0, "landmarks")  # fewer: make a keyframe early
    # larger rotation since the last keyframe: make a keyframe early
    max_rotation_deg: float = setting(10.0, POSITIVE, "deg")
    # fewer: tracking is lost and re-initialised from the current lidar depth
    min_pnp_inliers: int = setting(15, Range(4), "inliers")
    # A solution with fewer inliers than this share of the last frame's is checked against matching without the
    # motion model (frontend.py); 0 disables.
    weak_inlier_share: float = setting(0.4, SHARE)
    # motion-model yaw offsets a rescue also tries
    rescue_yaw_deg: tuple[float, ...] = setting((6.0, -6.0, 12.0, -12.0), Range(-90.0, 90.0), "deg")
    ransac_reproj_px: float = setting(2.0, POSITIVE, "px")
    ransac_line_px: float = setting(2.0, POSITIVE, "px")
    ransac_iterations: int = setting(1000, COUNT, "iterations")
    # poselib's RANSAC sampling; fixed so that runs repeat, another value to see how far a result moves with the draw
    ransac_seed: int = setting(0, COUNT0, "seed")
    outlier_reproj_px: float = setting(3.0, POSITIVE, "px")
    # landmarks of recent keyframes re-found this close to their projection
    search_radius_px: float = setting(8.0, POSITIVE, "px")
    # how many recent keyframes' landmarks are searched for (0: previous frame only)
    search_keyframes: int = setting(2, COUNT0, "keyframes")
    # Line landmarks re-found by projection (plvo/tracking/search.py), beside the 2D-2D matches.
    search_lines: bool = True
    # both endpoints of a segment this close to the projected landmark line
    line_search_px: float = setting(4.0, POSITIVE, "px")
    line_search_angle_deg: float = setting(3.0, ANGLE, "deg")
    line_search_overlap: float = setting(0.3, SHARE)  # shared extent along the line, as a share of the shorter segment
    # Every this many keyframes the map drops the landmarks nothing can use any more (seen by one keyframe, out of
    # every back-end window and tracker search; LandmarkMap.drop_unreachable), so memory follows what is kept, not
    # the length of the run; 0 keeps them all.
    drop_unreachable_every: int = setting(10, COUNT0, "keyframes")


@dataclass(frozen=True)
class CrossCheckConfig:
    """The camera checked against the lidar (plvo.tracking.lidar_check, docs/crosscheck.md)."""

    enabled: bool = True
    at_keyframes: bool = True  # every keyframe's motion since the previous keyframe, beside the doubtful frames
    # scans downsampled this coarse reach 4 m steps from standing still (lidar_check.py)
    voxel_m: float = setting(1.5, POSITIVE, "m")
    min_range_m: float = setting(2.0, NON_NEGATIVE, "m")  # the car's own roof and mirrors
    max_range_m: float = setting(80.0, POSITIVE, "m")
    min_fitness: float = setting(0.5, SHARE)  # fewer source points with a target within a voxel: the lidar cannot judge
    # translation's information this ill-conditioned: the lidar cannot judge
    degenerate_ratio: float = setting(0.02, SHARE)
    # The camera agrees with the lidar within agree_m plus agree_share of the step and agree_deg
    agree_m: float = setting(0.3, POSITIVE, "m")
    agree_share: float = setting(0.1, NON_NEGATIVE)
    agree_deg: float = setting(1.5, POSITIVE, "deg")
    # A step this far from the motion model's (metres plus share of the predicted step; degrees) calls the lidar
    doubt_m: float = setting(0.5, POSITIVE, "m")
    doubt_share: float = setting(0.3, NON_NEGATIVE)
    doubt_deg: float = setting(3.0, POSITIVE, "deg")
    # mean absolute difference (grey levels) below which an image repeats the last
    frozen_image_grey: float = setting(0.5, NON_NEGATIVE, "grey levels")
    # the lidar moved less than this: the car stands (a repeated image is then no fault)
    still_m: float = setting(0.05, NON_NEGATIVE, "m")
    # a frame interval this many times the previous one: frames were dropped
    gap_factor: float = setting(1.5, Range(1.0, lo_open=True))
    # Camera-lidar time offset (plvo.tracking.time_offset): the lidar's scans taken time_offset_s after the images
    # (stated by the user where known; each scan is then moved to its image's instant); estimated from the checked
    # intervals' rotations within +-offset_max_s and named when observable (sigma below offset_sigma_s) and over
    # offset_warn_s from the stated one.
    time_offset_s: float = setting(0.0, Range(-0.5, 0.5), "s")
    estimate_time_offset: bool = True
    offset_max_s: float = setting(0.2, Range(0.0, 0.5, lo_open=True), "s")
    offset_sigma_s: float = setting(0.01, POSITIVE, "s")
    offset_warn_s: float = setting(0.02, NON_NEGATIVE, "s")
    # ...and named only when it is that far by this many of its standard deviations too: the first observable estimate
    # on the realistic twin of KITTI 02, -21 +- 6 ms from 15 intervals (the twin's offset is -3 ms; -10 +- 2 ms a few
    # seconds on), was named and the run started again with it
    offset_confidence_sigmas: float = setting(3.0, NON_NEGATIVE)
    # A found offset is used by running again from the first frame with it stated (the run loops of plvo.runtime.run and
    # plvo-viz): moving the scans mid-run mixed the frames before it with those after (docs/crosscheck.md)
    restart_on_offset: bool = True
    # Camera-lidar extrinsic (plvo.tracking.extrinsic): a rotation (vector, degrees, the camera's frame) applied to the
    # calibration's T_cam_velo before anything uses it (a correction known, or the one a restart found); estimated
    # from the checked intervals (a zero-mean prior of extrinsic_prior_deg a component keeps what nothing excited at
    # the stated one), reported in timings.json, and named when a component departs by extrinsic_warn_deg and
    # extrinsic_confidence_sigmas of its standard deviations. Named only when gross: the camera's own motion follows
    # the stated extrinsic in part (its depth priors are the scan seen through it), so an error is read short or long
    # (on the realistic twin of 04, 0.4 deg of yaw injected moved the reading by 0.18), and real 04's reading (-0.31 /
    # +0.30 deg of pitch / yaw) is the lidar registrations' own: applied, it made the clip's figures worse
    # (docs/crosscheck.md)
    extrinsic_correction_deg: tuple[float, ...] = setting((0.0, 0.0, 0.0), Range(-5.0, 5.0), "deg")
    estimate_extrinsic: bool = True
    extrinsic_prior_deg: float = setting(1.0, POSITIVE, "deg")
    extrinsic_warn_deg: float = setting(0.5, NON_NEGATIVE, "deg")
    extrinsic_confidence_sigmas: float = setting(3.0, NON_NEGATIVE)
    # A gross extrinsic error found is used by running again from the first frame with it corrected, as an offset is
    restart_on_extrinsic: bool = True


@dataclass(frozen=True)
class RegistrationConfig:
    method: RegistrationMethod = "ndt"  # "ndt", or "icp" / "gicp" directly
    fallback: RegistrationMethod | Literal["none"] = "icp"  # used when NDT fails; "none" to disable
    # as accurate as 0.5 on 04 with 2/3 of the points (docs/results/defaults.md)
    voxel_m: float = setting(0.6, POSITIVE, "m")
    ndt_resolution_m: float = setting(1.0, POSITIVE, "m")
    max_iterations: int = setting(30, COUNT, "iterations")
    max_range_m: float = setting(60.0, POSITIVE, "m")
    max_correspondence_m: float = setting(1.0, POSITIVE, "m")
    min_range_m: float = setting(2.0, NON_NEGATIVE, "m")  # drop returns from the car itself
    # a first NDT pass at this resolution widens the basin; 0 disables
    ndt_coarse_resolution_m: float = setting(3.0, NON_NEGATIVE, "m")
    min_fitness: float = setting(0.3, SHARE)  # fewer source points with an NDT/ICP correspondence: registration failed
    # a result this far from the initial guess (translation) counts as failed
    max_jump_m: float = setting(1.5, POSITIVE, "m")
    max_jump_deg: float = setting(5.0, POSITIVE, "deg")
    # "inverse": exp(-2 (e_bar/e_hat)^2), so that a registration worse than the tracker's pose gets a small weight
    # (plvo/lidar/registration.py, docs/results/defaults.md); "paper": exp(-2 (e_hat/e_bar)^2) as printed.
    zeta_formula: Literal["paper", "inverse"] = "inverse"
    # Motion compensation of each scan's sweep before registration (plvo.lidar.deskew), from the tracker's motion:
    # "auto" deskews the scans the dataset says are not compensated (Dataset.scans_compensated), "on" always,
    # "off" never.
    deskew: Literal["auto", "on", "off"] = "auto"


@dataclass(frozen=True)
class BackendConfig:
    enabled: bool = True  # False: odometry alone (the tracker's poses, no registration or bundle adjustment)
    # Lidar registration between consecutive keyframes (paper II-D's alignment): the relative-pose factors of the
    # scale correction and of the bundle adjustment. Off together with scale_correction is the paper's Ours (#).
    registration: bool = True
    scale_correction: bool = True  # the scale correction optimisation (II-D) before the bundle adjustment
    window_keyframes: int = setting(8, Range(2), "keyframes")
    sigma_point_px: float = setting(0.1, POSITIVE, "px")  # paper, III: Sigma^P = 0.1 I (the paper's factor covariance)
    sigma_line: float = setting(0.2, POSITIVE, "px")  # paper, III: Sigma^L = 0.2 I
    # The paper's relative-pose information zeta I as zeta / sigma^2 per component: small enough that the lidar,
    # not the point factors, sets scale and direction of travel (docs/config.md#backend, docs/results/defaults.md)
    sigma_relative_pose: float = setting(0.0001, POSITIVE, "m")
    sigma_relative_rotation_deg: float = setting(0.0003, POSITIVE, "deg")
    # Both sigmas grow as (e_bar / relative_pose_residual_m)^power, e_bar the residual (backend.worker.residual_weight):
    # a third power meets the twins' and real 04's alignments (docs/config.md#backend, docs/results/defaults.md)
    relative_pose_residual_m: float = setting(0.04, POSITIVE, "m")
    relative_pose_residual_power: float = setting(3.0, NON_NEGATIVE)
    # The rotation's sigma grows with its own, smaller power: at the translation's, the tracker's heading pulled the
    # realistic twins (docs/config.md#backend, docs/results/rotation_weight/)
    relative_rotation_residual_power: float = setting(1.0, NON_NEGATIVE)
    # Virtual baseline of the depth-prior (stereo-form) point factors: their depth weight grows with b^2. KITTI's
    # 0.54: a smaller one gave worse rotations on 04 and worse errors on the towns (docs/results/defaults.md).
    stereo_baseline_m: float = setting(0.54, POSITIVE, "m")
    # A depth prior's own sigma is this times its plane fit's rms (the returns' spread about the patch), added to
    # what sigma_point_px allows at its depth: a rough patch (foliage, a kerb's edge) weighs less. 0: unweighted.
    # 4 was the best of 0-8 on real 04 (docs/config.md#backend, docs/results/depth_prior_weight/)
    depth_prior_rms_factor: float = setting(4.0, NON_NEGATIVE)
    huber_point: float = setting(2.0, POSITIVE, "px")
    huber_line: float = setting(2.0, POSITIVE, "px")
    # as accurate as 5 and 10, in less time (docs/config.md#backend, docs/results/cheaper_backend/,
    # docs/results/faster_config/)
    iterations: int = setting(3, COUNT, "iterations")
    # Observations whose residual is still over this after the first LM round are left out of a second round
    # (bundle_adjustment.py); 0 disables. A lidar depth 5 % off at 10 m is 1.9 px in the stereo row.
    outlier_px: float = setting(4.0, NON_NEGATIVE, "px")
    concurrent: bool = True  # run the back end and the loop closer beside the tracker (False: inline, lag 0)
    # Where the concurrent workers run (plvo.runtime.workers): "process" (no GIL shared with the tracker; the
    # features are then extracted in a process of their own too, plvo.features.worker) or "thread".
    executor: Literal["process", "thread"] = "process"
    # How long the run waits for a silent worker whose result is due before failing the run, naming it: a wide
    # margin over the slowest job measured (docs/config.md#backend, docs/results/soak/)
    worker_timeout_s: float = setting(300.0, POSITIVE, "s")
    # A keyframe's back-end result is applied this many frames later (or at the next keyframe): a fixed point of the
    # run, late enough for the next keyframe to be tracked meanwhile (docs/config.md#backend, docs/results/defaults.md)
    max_lag_frames: int = setting(6, COUNT0, "frames")
    # What a keyframe's scan is registered to for the relative-pose factors (plvo.lidar.local_map): "local_map", a
    # voxel map of the last local_map_keyframes keyframes' scans in the world frame, or "keyframe", the previous
    # keyframe's scan alone (NDT keyframe to keyframe).
    lidar_target: Literal["local_map", "keyframe"] = "local_map"
    local_map_keyframes: int = setting(10, COUNT, "keyframes")
    local_map_voxel_m: float = setting(0.5, POSITIVE, "m")
    # Source points a map alignment uses at most (evenly thinned): as exact as all of a KITTI scan's, and a denser
    # lidar costs the same (docs/config.md#backend, docs/results/cheaper_backend/)
    local_map_source_points: int = setting(2000, Range(100), "points")


@dataclass(frozen=True)
class LoopConfig:
    enabled: bool = True
    min_keyframe_gap: int = setting(30, COUNT0, "keyframes")  # ignore candidates among the last keyframes
    min_score: float = setting(0.3, NON_NEGATIVE)
    consistency: int = setting(3, COUNT, "keyframes")  # consecutive keyframes that must agree
    min_inliers: int = setting(30, Range(4), "inliers")
    # The loop closer's detection and verification (plvo/loop/).
    vocab_dir: str = ""  # folder with orb.npz / lbd.npz; empty: the shipped plvo/assets/vocab
    # skip the query when even the previous keyframe scores below this
    min_neighbour_score: float = setting(0.005, NON_NEGATIVE)
    # normalise by the best combined score among this many previous keyframes
    neighbours: int = setting(1, COUNT, "keyframes")
    # candidates this close in keyframe id form one island (DBoW2 group)
    island_gap: int = setting(3, COUNT0, "keyframes")
    max_verify: int = setting(2, COUNT, "candidates")  # best candidates of the winning island checked geometrically
    # keyframes after an accepted loop during which no new loop is verified
    loop_cooldown: int = setting(5, COUNT0, "keyframes")
    ratio: float = setting(0.8, RATIO)  # Lowe ratio for ORB / LBD matches between the two keyframes
    point_max_hamming: int = setting(64, HAMMING, "bits")
    line_max_hamming: int = setting(80, HAMMING, "bits")
    ransac_px: float = setting(3.0, POSITIVE, "px")  # PnP/PnL RANSAC and inlier threshold between the keyframes (px)
    use_registration: bool = True  # refine the PnP/PnL pose by scan registration when scans are given
    # PnP/PnL inliers (3D) off their dominant plane: rejects tiled ground textures
    min_off_plane: int = setting(10, COUNT0, "inliers")
    plane_tolerance_m: float = setting(0.3, POSITIVE, "m")
    odom_sigma_rot: float = setting(0.01, POSITIVE, "rad")  # pose-graph sigmas of a keyframe-to-keyframe edge (rad, m)
    odom_sigma_trans: float = setting(0.05, POSITIVE, "m")
    loop_sigma_rot: float = setting(0.01, POSITIVE, "rad")  # and of a verified loop edge
    loop_sigma_trans: float = setting(0.05, POSITIVE, "m")
    pgo_iterations: int = setting(100, COUNT, "iterations")
    global_ba: bool = True  # a global bundle adjustment of poses and points after the pose graph (global_ba.py)
    global_ba_iterations: int = setting(10, COUNT, "iterations")
    # observations further from their landmark's projection are left out
    global_ba_max_px: float = setting(8.0, POSITIVE, "px")
    # Points in the global BA at most, the same share for every keyframe (global_ba.point_budget); 0: all.
    global_ba_max_points: int = setting(15000, COUNT0, "points")
    # A global BA moving a keyframe from the pose graph's solution more than max_move_m + move_fraction x its largest
    # correction is not applied (global_ba.implausible): right results stay within, wrong ones not (docs/config.md#loop)
    global_ba_max_move_m: float = setting(2.0, NON_NEGATIVE, "m")
    global_ba_move_fraction: float = setting(1.0, NON_NEGATIVE)
    # A verified loop corrects the query keyframe by at most max_drift_fraction x the distance driven since the match
    # + max_drift_floor_m: the town's repeated buildings gave false loops (docs/config.md#loop). 0 disables.
    max_drift_fraction: float = setting(0.1, NON_NEGATIVE)
    max_drift_floor_m: float = setting(2.0, NON_NEGATIVE, "m")
    # Two keyframes that see one place are at most this far apart: a longer loop edge is refused, and a candidate
    # the odometry puts further away than its drift bound plus this is refused before verification.
    max_view_m: float = setting(40.0, POSITIVE, "m")
    # Lidar place recognition beside the bags of words (plvo.loop.lidar_place, map-closures' density maps, which
    # find a place whichever way it is driven), verified by scan registration alone.
    lidar_place: bool = True
    # A place node every this much driving: overlapping local maps at a small memory and query cost
    # (docs/config.md#loop, plvo/loop/lidar_place.py)
    lidar_place_spacing_m: float = setting(10.0, NON_NEGATIVE, "m")
    # A keyframe's local map: the scans this far before and after it (a node waits until the car is this far past it);
    # more inliers than maps behind the keyframe alone (docs/config.md#loop, plvo/loop/lidar_place.py)
    lidar_place_reach_m: float = setting(20.0, NON_NEGATIVE, "m")
    # Local maps cropped to this radius: smaller crops found fewer inliers (docs/config.md#loop,
    # plvo/loop/lidar_place.py)
    lidar_place_radius_m: float = setting(70.0, POSITIVE, "m")
    # local map voxel and density image pixel: map_closures', coarser ones found less (docs/config.md#loop)
    lidar_place_voxel_m: float = setting(0.5, POSITIVE, "m")
    # ORB matches between density images within this Hamming distance: cheaper than map_closures' 50, without the
    # true matches 30 lost (docs/config.md#loop, plvo/loop/lidar_place.py)
    lidar_place_hamming: int = setting(40, HAMMING, "bits")
    # map_closures' own threshold: between other places' counts and true revisits' (docs/config.md#loop)
    lidar_place_min_inliers: int = setting(5, Range(3), "inliers")
    # Verification by registering the two keyframes' local maps (plvo.loop.map_registration): of the query's map
    # the points within this radius, which the candidate's map (the same place seen from up to 40 m) covers.
    scan_verify_radius_m: float = setting(40.0, POSITIVE, "m")
    # Share of the query's points matched: below true revisits', above a corner seen from two streets with a wrong
    # edge (docs/config.md#loop, docs/results/defaults.md)
    scan_min_overlap: float = setting(0.5, SHARE)
    # RMS point-to-plane distance (each capped at 0.5 m): above true revisits', deskewed or swept (docs/config.md#loop,
    # plvo/loop/map_registration.py)
    scan_max_error_m: float = setting(0.15, POSITIVE, "m")
    # Smallest eigenvalue of the point-to-plane Hessian per point (rotations at a 10 m lever): below it (a corridor)
    # nothing is registered, above it the restarts decide (docs/config.md#loop, docs/results/faster_config/)
    scan_min_constraint: float = setting(0.005, NON_NEGATIVE)
    # ICP restarted this far to either side along the least constrained direction must come back within
    # scan_unique_m, as true revisits do and other places lined up do not (docs/config.md#loop)
    scan_basin_m: float = setting(3.0, NON_NEGATIVE, "m")
    scan_unique_m: float = setting(0.3, POSITIVE, "m")
    # A scan-verified loop edge joins keyframes at most this far apart (a further candidate hands it to its neighbour
    # nearest the query): as far as local maps reach (docs/config.md#loop, docs/results/defaults.md)
    scan_max_edge_m: float = setting(20.0, POSITIVE, "m")
    # A bag-of-words candidate refused for too few image matches with depth or PnP/PnL inliers is registered too,
    # from the odometry's relative pose: only a keyframe's best, registrations being costly (docs/config.md#loop)
    scan_fallback: bool = True
    # Concurrent runs: a keyframe's loop result is applied this many frames after it, a global BA's this many frames
    # after the loop correction it follows (fixed points of the run: the tracker waits there if the worker is late).
    max_lag_frames: int = setting(20, COUNT0, "frames")
    global_ba_lag_frames: int = setting(100, COUNT0, "frames")


@dataclass(frozen=True)
class SystemConfig:
    orb: OrbConfig = field(default_factory=OrbConfig)
    lines: LineConfig = field(default_factory=LineConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    crosscheck: CrossCheckConfig = field(default_factory=CrossCheckConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)

    def sections(self, part: type[P]) -> P:
        """The sections a part is built from (`part`'s fields name them): each part is given its own, not the whole."""
        return part(**{name: getattr(self, name) for name in part._fields})


class TrackerSections(NamedTuple):
    """What the frame-to-frame tracker (plvo.tracking.frontend.Frontend) is built from."""

    orb: OrbConfig
    lines: LineConfig
    matching: MatchingConfig
    depth: DepthConfig
    tracking: TrackingConfig  # keyframes, PnP/PnL, the search by projection
    crosscheck: CrossCheckConfig
    registration: RegistrationConfig  # whether the scans the priors come from are deskewed


class BackendSections(NamedTuple):
    """What the back end (plvo.backend.worker.BackendCore) is built from."""

    backend: BackendConfig
    registration: RegistrationConfig
    tracking: TrackingConfig  # which features the tracker keeps (points only, depth priors): what the window holds


class LoopSections(NamedTuple):
    """What the loop closer (plvo.loop.worker.LoopCore) is built from."""

    loop: LoopConfig
    backend: BackendConfig  # the global bundle adjustment weighs its factors as the back end does
    registration: RegistrationConfig
    tracking: TrackingConfig  # whether landmarks carry depth priors


P = TypeVar("P", TrackerSections, BackendSections, LoopSections)


# The paper's ablations, as overrides of the full system.
ABLATIONS: dict[str, dict[str, dict[str, Any]]] = {
    "full": {},
    "no_depth_priors": {"tracking": {"use_depth_priors": False}},
    # The paper's Ours (#), "without the scale correction module": II-D is the registration and the optimisation
    # that fuses it, and II-E takes its relative poses from II-D, so without the module the bundle adjustment has no
    # relative-pose factors either (the only reading under which the paper's 1.95 % vs 0.94 % can arise).
    "no_scale_correction": {"backend": {"registration": False, "scale_correction": False}},
    "points_only": {"tracking": {"points_only": True}},
    # Not one of the paper's: the frame-to-frame tracker alone (no back end, no loop closing), the baseline the
    # full system must beat.
    "tracker_only": {"backend": {"enabled": False}, "loop": {"enabled": False}},
    # Not one of the paper's: the scale correction optimisation alone switched off, the registration factors kept in
    # the bundle adjustment (which then fixes the scale itself; see plvo/backend/worker.py).
    "no_scale_step": {"backend": {"scale_correction": False}},
    # Each lidar-side component alone switched off: the raw (swept) scans, keyframe-to-keyframe NDT instead of the
    # local map, and loops from the bags of words only (no lidar place recognition).
    "no_deskew": {"registration": {"deskew": "off"}},
    "keyframe_ndt": {"backend": {"lidar_target": "keyframe"}},
    "no_lidar_loops": {"loop": {"lidar_place": False}},
}


def _from_dict(cls: type, data: dict[str, Any], prefix: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in fields:
            raise ConfigError(f"unknown config key '{name}'")
        want = hints[key]
        if isinstance(want, type) and dataclasses.is_dataclass(want):
            if not isinstance(value, dict):
                raise ConfigError(f"config key '{name}' must be a table")
            kwargs[key] = _from_dict(want, value, f"{name}.")
            continue
        if typing.get_origin(want) is tuple:  # a list of numbers in TOML
            if not isinstance(value, (list, tuple)) or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                raise ConfigError(f"config key '{name}' must be a list of numbers, got {value!r}")
            kwargs[key] = tuple(float(v) for v in value)
            continue
        if choices_of(want):  # a choice: refused by check_ranges when not among its type's values
            kwargs[key] = value
            continue
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or (want is int and isinstance(value, bool)):
            raise ConfigError(f"config key '{name}' must be {want.__name__}, got {type(value).__name__}")
        kwargs[key] = value
    return cls(**kwargs)


def config_from_dict(data: dict[str, Any]) -> SystemConfig:
    """Build a config from nested dicts; unknown keys, wrong types and values out of their range
    (plvo.config_fields) raise ConfigError naming the dotted key."""
    cfg = _from_dict(SystemConfig, data, "")
    check_ranges(cfg)
    return cfg


def merge(base: SystemConfig, overrides: dict[str, Any]) -> SystemConfig:
    """Return `base` with the nested `overrides` applied (validated like a file)."""
    merged = config_to_dict(base)
    for section, values in overrides.items():
        if not isinstance(values, dict):
            raise ConfigError(f"config key '{section}' must be a table")
        merged.setdefault(section, {}).update(values)
    return config_from_dict(merged)


def with_ablation(base: SystemConfig, name: str) -> SystemConfig:
    if name not in ABLATIONS:
        raise ConfigError(f"unknown ablation '{name}' (choose from {', '.join(ABLATIONS)})")
    return merge(base, ABLATIONS[name])


def load_config(path: str | os.PathLike[str] | None) -> SystemConfig:
    """Read a TOML config; None gives the defaults."""
    if path is None:
        return SystemConfig()
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML ({exc})") from None
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def config_to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def config_to_toml(cfg: SystemConfig) -> str:
    import tomli_w

    return tomli_w.dumps(config_to_dict(cfg))


def save_config(cfg: SystemConfig, path: str | os.PathLike[str]) -> None:
    """Write the resolved config as TOML, atomically."""
    write_text_atomic(Path(path), config_to_toml(cfg))
