"""Loop closure at sequence scale: detection precision and recall, and what each correction step buys.

For every sequence it runs the System three times (back end inline, deterministic order): without loop closing,
with the pose graph only (loop.global_ba = false), and with pose graph + global bundle adjustment (the default).
Ground-truth revisits: a keyframe within 5 m and 30 deg of a keyframe more than loop.min_keyframe_gap keyframes
back. Precision: accepted loops joining a true revisit / accepted loops. Recall: revisit passages (runs of
consecutive revisiting keyframes) with at least one accepted loop / passages; and keyframes within cooldown
reach of an accepted loop / revisiting keyframes. Errors: ATE (SE(3)-aligned RMSE) and end-point error of cam0.

    .venv/bin/python scripts/loop_eval.py --root data/town --seq 21 22 --only-loop 20 --out results/loops.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

SETTINGS = {"no_loop": {"enabled": False}, "pose_graph": {"global_ba": False}, "pose_graph_global_ba": {}}


class _Collect:
    def __init__(self) -> None:
        self.loops, self.kf_frame = [], {}

    def on_run_start(self, info) -> None:
        pass

    def on_frame(self, frame) -> None:
        pass

    def on_stage(self, frame_index, result) -> None:
        from plvo.results import KeyframeResult, LoopResult

        if isinstance(result, LoopResult):
            self.loops.append(result)
        elif isinstance(result, KeyframeResult):
            self.kf_frame[result.keyframe_id] = result.frame_index

    def close(self) -> None:
        pass


def _run(root: str, seq: str, setting: str) -> dict:
    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.run import run_dataset
    from plvo_eval.kitti_metric import evaluate_sequence
    from plvo_eval.revisits import detection_stats
    from plvo_eval.tasks import anchor, metrics_dict

    cfg = merge(SystemConfig(), {"backend": {"concurrent": False}, "loop": SETTINGS[setting]})
    ds = KittiOdometry(root, seq)
    rec = _Collect()
    out = run_dataset(ds, cfg, rec)
    gt = ds.gt_T_world_cam
    est = anchor(out.poses, gt[0])
    metrics = metrics_dict(evaluate_sequence(gt, est), gt, est)
    res = {"sequence": seq, "setting": setting, "ate_m": metrics["ate_m"], "end_point_m": metrics["final_drift_m"],
           "n_keyframes": out.n_keyframes, "n_lost": out.n_lost,
           # medians over the keyframes where the stage ran (a correction step runs only after a loop)
           "timings_ms": {k: float(1e3 * np.median(np.asarray(v)[np.asarray(v) > 0])) for k, v in out.timings.items()
                          if k.startswith("loop") and np.any(np.asarray(v) > 0)}}
    if setting == "no_loop":
        return res
    accepted = [r for r in rec.loops if r.accepted]
    res["accepted"] = [(r.query_keyframe, r.match_keyframe, r.frame_index) for r in accepted]
    res.update(detection_stats(gt, rec.kf_frame, [(r.query_keyframe, r.match_keyframe) for r in accepted],
                               cfg.loop.min_keyframe_gap, cfg.loop.loop_cooldown))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", required=True)
    ap.add_argument("--seq", nargs="+", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS),
                    help="for every --seq; --only-loop SEQ runs just the default setting on SEQ")
    ap.add_argument("--only-loop", nargs="*", default=[], metavar="SEQ",
                    help="sequences to run with the default setting only (e.g. one that never revisits)")
    a = ap.parse_args(argv)
    from plvo.atomic import write_text_atomic

    jobs = [(a.root, s, k) for s in a.seq for k in a.settings]
    jobs += [(a.root, s, "pose_graph_global_ba") for s in a.only_loop]
    with ProcessPoolExecutor(a.workers) as pool:
        results = list(pool.map(_run, *zip(*jobs)))
    write_text_atomic(a.out, json.dumps(results, indent=1))
    for r in results:
        print(json.dumps({k: v for k, v in r.items() if k != "accepted"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
