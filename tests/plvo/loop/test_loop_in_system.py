"""Loop closure inside the whole System: run_dataset with inline workers over a short synthetic loop.

The sequence (seed 177, 150 frames at 15 m/s) circles the town's smallest block near the start, a 180 m lap, then
drives 44 m along the first street again. The System runs over its first RUN_FRAMES frames, where it closes the
revisit (first at frame 108, as the car comes back within 7 m of the first street's first keyframe: a bag-of-words
candidate without enough image matches, registered by the lidar). Cost: the generation of the 150 frames plus about
70 s of CPU for the run.

Inline workers (`backend.concurrent = False`) make the run deterministic and identical to a run without the loop
closer until the first accepted loop. So the keyframe trajectory the back end reports just before the correction
is what the System without loop closure has at that frame, and the frames before the revisit are a run over a
sequence that never revisits.
"""

from __future__ import annotations

import numpy as np
import pytest
from stage_collector import Collect

from plvo.config import BackendConfig, LoopConfig, SystemConfig
from plvo.results import EdgeKind
from plvo_eval.revisits import loop_edge_errors, revisits

pytestmark = pytest.mark.slow

FRAMES, SEED, SPEED = 150, 177, 15.0
RUN_FRAMES = 136
REVISIT_DEG = 30.0  # a keyframe revisits an earlier one seen this close in heading (and more than min gap back)


@pytest.fixture(scope="module")
def run(synth_sequence_factory):
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.run import run_dataset

    root = synth_sequence_factory(FRAMES, seed=SEED, speed_mps=SPEED, loop=True)
    ds = KittiOdometry(root, "00", frames=slice(0, RUN_FRAMES))
    rec = Collect()
    cfg = SystemConfig(backend=BackendConfig(concurrent=False), loop=LoopConfig(enabled=True))
    return ds, run_dataset(ds, cfg, rec), rec


def _revisits(gt: np.ndarray, kf_frame: dict[int, int], gap: int) -> dict[int, set[int]]:
    """Keyframe id -> ids of keyframes more than `gap` back that it revisits (ground truth): as close as a loop edge
    may join them (loop.scan_max_edge_m), seen within REVISIT_DEG of one another."""
    return revisits(gt, kf_frame, gap, LoopConfig().scan_max_edge_m, REVISIT_DEG)


def test_loop_is_closed_and_end_point_error_falls(run):
    ds, out, rec = run
    gt = ds.gt_T_world_cam
    accepted = [r for r in rec.loops if r.accepted]
    assert accepted, "the revisit of the first street was not closed"
    for r in accepted:  # precision: every accepted loop joins two views of one place and relates them rightly
        (edge,) = loop_edge_errors(gt, rec.kf_frame, [(r.match_keyframe, r.query_keyframe, r.T_match_query)])
        assert edge["true"] and edge["edge_error_m"] < 0.05, (r.query_keyframe, r.match_keyframe, edge)
        assert edge["true_distance_m"] <= LoopConfig().scan_max_edge_m, edge
    # At the first loop: the back end's keyframe trajectory just before the correction (what the System without
    # loop closure has then) and the loop closer's corrected one; their newest keyframe is the end point.
    first = accepted[0]
    graphs = [g for g in rec.graphs if g.frame_index == first.frame_index]
    # back end, the loop correction, the global bundle adjustment after it
    assert len(graphs) == 3 and graphs[1].edge_kind.max() == EdgeKind.LOOP
    fq = rec.kf_frame[first.query_keyframe]
    before, graph, adjusted = (float(np.linalg.norm(g.T_world_cam[first.query_keyframe, :3, 3] - gt[fq, :3, 3]))
                               for g in graphs)
    # measured 0.037 m before, 0.019 after the pose graph and 0.011 after the global bundle adjustment at the
    # defaults on the Intel Xeon machine (the loop closes as the car comes back within 7 m of the first street's
    # first keyframe), 0.0346, 0.0193 and 0.0117 on the AMD EPYC one (the same code's last bits differ); 0.036,
    # 0.0097 and 0.0062 with the previous defaults (LSD at 0.5, 8 ORB levels, 5 BA iterations). The bounds leave
    # both machines 15-20 % of margin: the adjustment gains on the pose graph and takes the error below 40 %.
    assert graph < before and adjusted < 0.75 * graph and adjusted < 0.4 * before and adjusted < 0.015, \
        (before, graph, adjusted)
    # The map holds the correction, the System's poses carry it and the tracker went on from the corrected map
    # without losing track: the frames from the loop on stay as close to the truth as after the correction. They
    # include the loop keyframes' own frames, whose poses System.step keeps relative to their keyframes from before
    # the inline workers move them: taken after, such a frame would keep its uncorrected pose.
    assert not rec.lost, rec.lost
    err = np.linalg.norm(out.poses[:, :3, 3] - gt[:, :3, 3], axis=1)
    later = np.arange(fq, len(err))
    assert {r.frame_index for r in accepted} <= set(later.tolist())
    # measured 0.025 m (frame 130; the loop frames 118 and 133: 0.002 and 0.008 m); with the keyframe frames' poses
    # taken after the correction, frame 118 reads 0.125 m
    assert err[later].max() < 0.1, (err[later].max(), int(later[np.argmax(err[later])]))
    # The global bundle adjustment ran after each correction (its result is in the map the errors above read).
    gba = np.asarray(out.timings["loop_global_ba"])
    assert (gba > 0).sum() == len(accepted), gba[gba > 0]


def test_no_loop_before_the_revisit(run):
    ds, out, rec = run
    revisits = _revisits(ds.gt_T_world_cam, rec.kf_frame, LoopConfig().min_keyframe_gap)
    first_revisit = min(rec.kf_frame[q] for q in revisits)
    before = [r for r in rec.loops if r.frame_index < first_revisit]
    assert not [r for r in before if r.accepted], [(r.query_keyframe, r.match_keyframe) for r in before]
    # The closer was really asked (one query a keyframe), and candidates reached geometric verification before
    # the revisit: "no loop" there is the verification's verdict, not an idle detector.
    assert len(out.timings["loop_query"]) == out.n_keyframes
    assert len(before) >= 5 and all(r.reason for r in before)
