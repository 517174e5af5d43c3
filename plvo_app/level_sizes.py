"""How many bytes a frame each recording level costs: one run recorded at every level side by side (`plvo bench`),
and what a whole KITTI 00 (4541 frames) would weigh at the default level.

Above both the levels (plvo_app.recording_levels) and the recorder that applies them (plvo_app.rerun_recorder).
"""

from __future__ import annotations

import math
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

from plvo.recording import FanOut, RunInfo
from plvo.runtime.system import System
from plvo_app.recording_levels import LEVELS, DetailOptions
from plvo_app.rerun_recorder import ENTITIES, RerunOptions, RerunRecorder

LONG_RUN = 4541  # frames of KITTI 00, the longest odometry sequence
BUDGET_MB = 25.0  # a whole KITTI 00 at the default level: a file a person attaches to a bug report
# The thin scan and image's share of it, a keyframe (RerunOptions.thin_every_keyframes = 1: every one has them): the
# budget less the rest of a whole KITTI 00 at the default level (estimate_long_run on the synthetic town's 300 frames,
# the larger of it and KITTI 04's: 15.8 MB, of which 6.8 MB detail with every event window used), over the 1514
# keyframes KITTI 00 has at 04's rate: 9.2 MB / 1514 = 6.0 kB (measured: 5.45 kB on KITTI 04, 3.2 of scan and 2.3
# of image; 4.7 on the town, whose whole estimate is 23.7 MB)
THIN_BYTES_PER_THIN_KEYFRAME = 6000
# The long run's estimate takes a frame's bytes from the second half of the run: over fewer frames the chunks'
# schemas and the statics weigh in (6 KITTI frames made 58 MB of 51 frames' 23)
MIN_FRAMES_TO_EXTRAPOLATE = 50
THIN_ENTITIES = ("/world/camera/image/keyframe", "/world/lidar/thin/")  # the keyframes' thin image and scan


class _Prefix:
    """A recorder that sees the frames before `stop` only (and the late results that belong to them): the same run
    cut shorter, recorded side by side, so that the difference of the two says what a frame adds."""

    def __init__(self, recorder: RerunRecorder, stop: int):
        self.recorder, self.stop = recorder, stop

    def on_run_start(self, info: RunInfo) -> None:
        self.recorder.on_run_start(info)

    def on_restart(self, info: RunInfo) -> None:
        self.recorder.on_restart(info)

    def on_frame(self, frame) -> None:
        if frame.index < self.stop:
            self.recorder.on_frame(frame)

    def on_stage(self, frame_index: int, result) -> None:
        if frame_index < self.stop:
            self.recorder.on_stage(frame_index, result)

    def close(self) -> None:
        self.recorder.close()


def entity_bytes(path: str | Path) -> dict[str, int]:
    """Bytes of each entity's chunks in a recording (Arrow's in-memory size: before the file's LZ4, which takes
    little off JPEG, PNG and float positions)."""
    from plvo_app.rrd_reader import read_chunks

    out: dict[str, int] = defaultdict(int)
    for chunk in read_chunks(path):
        out[chunk.entity_path] += chunk.to_record_batch().nbytes
    return dict(out)


def thin_bytes(path: str | Path) -> tuple[int, int]:
    """(bytes, keyframes) of the thin scans and images of a recording: their JPEG and PNG blobs and 40 bytes a row
    of index (row id, frame, sensor and log time)."""
    import pyarrow.compute as pc

    from plvo_app.rrd_reader import read_chunks

    total, frames = 0, set()
    for chunk in read_chunks(path, [f"{e}/**" if e.endswith("/") else e for e in THIN_ENTITIES]):
        if chunk.is_static or not chunk.entity_path.startswith(THIN_ENTITIES):
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith(":blob"):
                total += int(pc.sum(pc.list_value_length(batch.column(name).flatten())).as_py() or 0)
                total += 40 * batch.num_rows
        if "frame" in batch.schema.names:
            frames.update(batch.column("frame").to_pylist())
    return total, len(frames)


def _redraw_bytes(frames: int, keyframes: int, opt: RerunOptions) -> float:
    """Bytes of the summary's redraws over a run: the estimate (every frame's position, at most
    trajectory_max_points + 1), the keyframes (at most trajectory_max_points) and the whole graph (an odometry edge a
    keyframe, at most graph_summary_edges; 2 positions and a colour each), on the recorder's schedule (1 in
    min(summary_every_keyframes, k/4) keyframes). They grow with the run until their caps: a short run's bytes a
    frame miss most of them. 12 bytes a position (LZ4 takes little off floats)."""
    total, since = 0.0, 0
    per_kf = frames / max(keyframes, 1)
    for k in range(1, keyframes + 1):
        since += 1
        if since < min(opt.summary_every_keyframes, max(1, k // 4)):
            continue
        since = 0
        est = min(k * per_kf, opt.trajectory_max_points + 1)
        total += 12 * est + 12 * min(k, opt.trajectory_max_points) + 28 * min(k, opt.graph_summary_edges)
    return total


def estimate_long_run(sizes: dict[str, dict[str, Any]], paths: dict[str, Path], half: Path, n: int, n_half: int,
                      n_kf: int, n_kf_half: int, frames: int = LONG_RUN) -> dict[str, Any]:
    """The default level's bytes for a `frames`-frame run, from this run's recordings (see `how` in the answer)."""
    opt, detail = RerunOptions(), DetailOptions()
    s_full, s_half = sizes["summary"]["bytes"], half.stat().st_size
    share = n_kf / max(n, 1)  # the data's keyframe rate
    kf_long = share * frames
    # The summary level grows by its second half minus its first (its fixed cost, the properties, the statics and the
    # chunks' schemas, drops out); of that, the redraws are taken out and modelled to the long run's length.
    slope = (s_full - s_half) / max(n - n_half, 1)
    redraw_measured = _redraw_bytes(n, n_kf, opt) - _redraw_bytes(n_half, n_kf_half, opt)
    slope_flat = max(slope - redraw_measured / max(n - n_half, 1), 0.0)
    fixed = max(s_full - slope_flat * n - _redraw_bytes(n, n_kf, opt), 0.0)
    summary_long = fixed + slope_flat * frames + _redraw_bytes(frames, round(kf_long), opt)
    # Detail, from the full level: bytes a frame of the entities written every frame, a keyframe of the others
    # (their chunks' size, scaled by the file's compression); not the full level's own (the 3D scan)
    by = entity_bytes(paths["full"])
    ratio = sizes["full"]["bytes"] / max(sum(by.values()), 1)
    per_frame = per_kf = 0.0
    for entity, b in by.items():
        e = ENTITIES.get(entity.removeprefix("/"))
        if e is None or e.level != "detail":
            continue
        if e.when == "keyframe":
            per_kf += b * ratio / max(n_kf, 1)
        else:
            per_frame += b * ratio / max(n, 1)
    stride = math.ceil(kf_long / max(detail.keyframe_stride, 1))
    window = detail.before + detail.after + 1
    stride_bytes = stride * (per_frame + per_kf)
    events_bytes = detail.max_event_windows * window * (per_frame + share * per_kf)  # every window used
    total = summary_long + stride_bytes + events_bytes
    thin, thin_kfs = thin_bytes(paths["default"])
    return {
        "frames": frames, "keyframes": round(kf_long), "mb": total / 1e6, "budget_mb": BUDGET_MB,
        "mb_without_events": (total - events_bytes) / 1e6,
        "summary_mb": summary_long / 1e6, "stride_detail_mb": stride_bytes / 1e6,
        "event_detail_mb": events_bytes / 1e6, "fixed_kb": fixed / 1e3, "summary_bytes_per_frame": slope_flat,
        "redraws_mb": _redraw_bytes(frames, round(kf_long), opt) / 1e6, "detail_bytes_per_frame": per_frame,
        "detail_bytes_per_keyframe": per_kf,
        "thin_bytes_per_thin_keyframe": thin / max(thin_kfs, 1),
        "how": (f"the summary level's growth from frame {n_half} to {n} ({slope_flat:,.0f} bytes a frame, with this "
                f"data's keyframe share {share:.0%}: the thin scan and image included) over {frames} frames, plus its "
                f"fixed cost ({fixed / 1e3:,.0f} kB) and its redraws (estimate, keyframes, graph) grown to their "
                f"caps; plus the default's detail: {stride} stride keyframes and all {detail.max_event_windows} event "
                f"windows of {window} frames at the full level's detail bytes a frame ({per_frame:,.0f}) and a "
                f"keyframe ({per_kf:,.0f})"),
    }


def measure_levels(dataset, config, frames: int | None = None, out_dir: str | Path | None = None,
                   levels: tuple[str, ...] = LEVELS, keep: bool = False) -> dict[str, dict[str, Any]]:
    """Run `dataset` (its first `frames` frames) once, recorded at every level side by side; per level the bytes
    of the .rrd and bytes a frame (and what a 4541-frame run would weigh at that rate: a linear extrapolation).
    With all three levels and at least MIN_FRAMES_TO_EXTRAPOLATE frames, the default's entry also has `long_run`:
    the estimate for a whole KITTI 00 (estimate_long_run, from a fourth recording of the first half at the summary
    level). keep=True keeps the
    recordings in `out_dir` (<level>.rrd) instead of a temporary folder.

    For `plvo bench`: e.g. `report["recording_levels"] = measure_levels(dataset, cfg, 300)`.
    """
    n = len(dataset) if frames is None else min(int(frames), len(dataset))
    with tempfile.TemporaryDirectory(prefix="plvo-levels-", dir=out_dir) as tmp:
        if keep:
            tmp = str(Path(out_dir or "."))
        paths = {lv: Path(tmp) / f"{lv}.rrd" for lv in levels}
        recorders = [RerunRecorder(paths[lv], RerunOptions(detail=DetailOptions(level=lv))) for lv in levels]
        every = {"summary", "default", "full"} <= set(levels) and n >= MIN_FRAMES_TO_EXTRAPOLATE
        n_half = n // 2
        half = Path(tmp) / "summary-half.rrd"
        extra = [_Prefix(RerunRecorder(half, RerunOptions(detail=DetailOptions(level="summary"))),
                         dataset.frame_indices[n_half])] if every else []
        system = System(config, FanOut([*recorders, *extra]))
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
        out: dict[str, dict[str, Any]] = {}
        n_kf = recorders[0]._policy._n_keyframes if recorders else 0
        for lv, rec in zip(levels, recorders):
            size = paths[lv].stat().st_size
            out[lv] = {"frames": n, "bytes": size, "bytes_per_frame": size / max(n, 1),
                       "mb_per_4541_frames": size / max(n, 1) * LONG_RUN / 1e6,
                       "path": str(paths[lv]) if keep else "", "keyframes": n_kf, "events": len(rec._policy.events),
                       "event_windows": rec._policy.n_event_windows,
                       "detail_frames": len(rec._detail_frames)}
        if every and n_kf:
            n_kf_half = extra[0].recorder._policy._n_keyframes
            out["default"]["long_run"] = est = estimate_long_run(out, paths, half, n, n_half, n_kf, n_kf_half)
            out["default"]["mb_4541_estimate"] = est["mb"]
    return out
