"""How many bytes a frame each recording level costs: one run recorded at every level side by side (`plvo bench`).

Above both the levels (plvo_app.recording_levels) and the recorder that applies them (plvo_app.rerun_recorder).
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

from plvo.recording import FanOut, RunInfo
from plvo.system import System
from plvo_app.recording_levels import LEVELS, DetailOptions
from plvo_app.rerun_recorder import RerunOptions, RerunRecorder


def measure_levels(dataset, config, frames: int | None = None, out_dir: str | Path | None = None,
                   levels: tuple[str, ...] = LEVELS, keep: bool = False) -> dict[str, dict[str, float]]:
    """Run `dataset` (its first `frames` frames) once, recorded at every level side by side; per level the bytes
    of the .rrd and bytes a frame (and what a 4541-frame run would weigh at that rate: a linear extrapolation).
    keep=True keeps the recordings in `out_dir` (<level>.rrd) instead of a temporary folder.

    For `plvo bench`: e.g. `report["recording_levels"] = measure_levels(dataset, cfg, 300)`.
    """
    n = len(dataset) if frames is None else min(int(frames), len(dataset))
    with tempfile.TemporaryDirectory(prefix="plvo-levels-", dir=out_dir) as tmp:
        if keep:
            tmp = str(Path(out_dir or "."))
        paths = {lv: Path(tmp) / f"{lv}.rrd" for lv in levels}
        recorders = [RerunRecorder(paths[lv], RerunOptions(detail=DetailOptions(level=lv))) for lv in levels]
        system = System(config, FanOut(recorders))
        info = RunInfo(name="measure_levels", sequence=dataset.sequence, calib=dataset.calib,
                       frame_indices=tuple(dataset.frame_indices[:n]),
                       gt_T_world_cam=None if dataset.gt_T_world_cam is None else dataset.gt_T_world_cam[:n],
                       config={}, version="", git_revision="", command_line="measure_levels")
        system.start(info)
        try:
            for i in range(n):
                system.step(dataset[i])
            system.finish()
        finally:
            system.close()
        out = {}
        n_kf = recorders[0]._policy._n_keyframes if recorders else 0
        for lv, rec in zip(levels, recorders):
            size = paths[lv].stat().st_size
            out[lv] = {"frames": n, "bytes": size, "bytes_per_frame": size / max(n, 1),
                       "mb_per_4541_frames": size / max(n, 1) * 4541 / 1e6, "path": str(paths[lv]) if keep else "",
                       "keyframes": n_kf, "events": len(rec._policy.events),
                       "event_windows": rec._policy.n_event_windows}
        if {"summary", "default", "full"} <= set(out) and n_kf:
            # The default's event detail is bounded (it does not grow with frames); its stride keyframes grow, each
            # costing about a keyframe's share of the full level's detail.
            s, d, f = (out[lv]["bytes"] for lv in ("summary", "default", "full"))
            stride = DetailOptions().keyframe_stride
            more = max(0, math.ceil(n_kf * 4541 / n / stride) - math.ceil(n_kf / stride))
            out["default"]["mb_4541_estimate"] = (s / n * 4541 + (d - s) + more * (f - s) / n_kf) / 1e6
    return out
