"""plvo bench --soak's report (plvo_eval.soak) on a short synthetic run: windows, memory, errors, loops."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.config import SystemConfig, config_to_dict, merge
from plvo.recording import NullRecorder, RunInfo


def test_soak_report_describes_the_run(synth_sequence_factory, tmp_path):
    from plvo.data.kitti import KittiOdometry
    from plvo_eval.soak import run_soak

    ds = KittiOdometry(synth_sequence_factory(40, seed=3), "00")
    cfg = merge(SystemConfig(), {"loop": {"enabled": True}})
    info = RunInfo(name="soak", sequence="00", calib=ds.calib, frame_indices=ds.frame_indices,
                   gt_T_world_cam=ds.gt_T_world_cam, config=config_to_dict(cfg), version="test",
                   git_revision="test", command_line="test")
    rep = run_soak(ds, cfg, NullRecorder(), info, window=10)
    assert rep["frames"] == 40 and len(rep["windows"]) == 4
    w = rep["windows"]
    assert [x["first_frame"] for x in w] == [0, 10, 20, 30] and all(x["fps"] > 0 for x in w)
    assert all(x["rss_mb"] > 100 and x["rss_tree_mb"] >= x["rss_mb"] for x in w)
    # the worker processes are in the tree: the back end and the loop closer each hold their libraries
    assert w[-1]["rss_tree_mb"] > w[-1]["rss_mb"] + 100
    assert set(rep["rss_mb_at"]) == {"40"}
    # the worst window against the median one, as the windows' own figures give them
    fps = np.array([x["fps"] for x in w])
    assert rep["fps_window_worst"] == fps.min() and rep["fps_window_median"] == pytest.approx(np.median(fps), abs=1e-3)
    assert rep["worst_over_median"] == pytest.approx(fps.min() / np.median(fps), abs=2e-3)
    # the windows' frames a second are over the frames' time, which the run's wall time (finishing too) holds
    assert 40 / np.sum(10 / fps) >= 0.99 * rep["fps"]
    prov = rep["provenance"]
    assert len(prov["load_start"]) == 3 and len(prov["load_end"]) == 3 and prov["machine"]["cpu_count"] >= 1
    assert {"revision", "dirty", "command_line", "plvo_version", "started_utc", "finished_utc"} <= set(prov)
    # the tracked error per window and the final figures agree with a run that tracks this street
    assert all(x["error_m_max"] < 0.5 for x in w), [x["error_m_max"] for x in w]
    assert rep["final"]["ate_m"] < 0.2 and rep["final"]["short_t_err_pct"] < 2.0
    assert rep["tracking_losses"] == [] and rep["n_keyframes"] >= 10
    assert rep["loops"] == [] and rep["corrections"] == []  # a street without a revisit
