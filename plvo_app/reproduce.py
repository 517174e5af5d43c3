"""Turn a recording back into its run and say whether the run reproduces.

The recording holds the config (TOML), the dataset's identity (layout, sequence, root, frames, calibration), a
digest prefix of each input file (xxh3-128; sha256 in recordings made before it) and, optionally, the raw inputs
of a window (`inputs/*`). `reproduce` reruns those frames with that config, records the rerun at the summary level
(the per-frame poses, every stage's counts and the decision log, as the original has them) and compares: the first
frame whose pose departs by more than the tolerance, and the first stage result that changed (feature counts,
matches, inliers, depth priors, keyframe decisions, back-end and loop counts; timings are not compared).
"""

# The pipeline, the datasets and the viewers (gtsam, open3d, rerun, viser: plvo.runtime.system alone imports in ~1 s)
#  are imported inside the functions that use them: `plvo --help` imports every command module.
from __future__ import annotations

import json
import logging
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from plvo.config import SystemConfig, config_from_dict, config_to_dict
from plvo.errors import ConfigError, RecordingError
from plvo.geometry.se3 import inv, rotation_angle
from plvo.types import Frame
from plvo_app.rrd_reader import RrdData, open_rrd, read_rrd
from plvo_app.run_identity import calib_from_dict, calib_to_dict, decode_inputs, file_digest, input_files
from plvo_app.scene_common import _pose_from_row

log = logging.getLogger(__name__)

COMPARED = ["/world/camera", "/metrics/**", "/log"]
# pipeline order: at the first frame that differs, the earliest stage is named as the one that changed
STAGE_ORDER = ["features", "matching", "tracking", "keyframes", "depth", "map", "backend", "loop"]
# tracking counts that follow from the keyframe decision: a changed decision is named rather than these
KEYFRAME_CONSEQUENCES = {f"tracking/{n}": "map" for n in ("new_points", "new_lines")}


@dataclass
class Report:
    source: str  # where the inputs came from
    frames: list[int]
    notes: list[str] = field(default_factory=list)  # input mismatches, concurrency, a different start
    pose_frame: int | None = None  # first frame whose pose departs
    pose_diff: tuple[float, float] = (0.0, 0.0)  # (m, deg) there
    max_diff: tuple[float, float] = (0.0, 0.0)
    stage_frame: int | None = None  # first frame with a changed stage result
    stage: str = ""  # e.g. "tracking/point_inliers 120 -> 118"

    @property
    def reproduces(self) -> bool:
        return self.pose_frame is None and self.stage_frame is None

    def lines(self, tol_m: float, tol_deg: float) -> list[str]:
        out = [f"reran frames {self.frames[0]}..{self.frames[-1]} ({len(self.frames)}) from {self.source}",
               *self.notes]
        if self.reproduces:
            out.append(f"reproduces: every pose within {tol_m:g} m / {tol_deg:g} deg (largest difference "
                       f"{self.max_diff[0]:.2g} m / {self.max_diff[1]:.2g} deg) and every stage result equal")
            return out
        if self.pose_frame is not None:
            out.append(f"departs at frame {self.pose_frame}: pose differs by {self.pose_diff[0]:.3g} m / "
                       f"{self.pose_diff[1]:.3g} deg (tolerance {tol_m:g} m / {tol_deg:g} deg)")
        else:
            out.append(f"poses within {tol_m:g} m / {tol_deg:g} deg, but a stage result changed")
        if self.stage_frame is not None:
            out.append(f"first changed stage result: frame {self.stage_frame}: {self.stage}")
        return out


def recorded_config(data: RrdData, overrides: dict[str, Any], path: Path) -> SystemConfig:
    text = data.properties.get("plvo:config")
    if not text:
        raise RecordingError(f"{path}: the recording holds no config (made before plvo recorded it)")
    try:
        cfg = config_from_dict(tomllib.loads(str(text)))
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise RecordingError(f"{path}: the recorded config does not load in this version ({exc})") from None
    merged = config_to_dict(cfg)
    for key, value in overrides.items():
        section, _, name = key.partition(".")
        if not name or section not in merged or name not in merged[section]:
            raise ConfigError(f"--set {key}: no such config key (expected section.key, e.g. orb.n_features)")
        merged[section][name] = value
    return config_from_dict(merged)


def parse_set(items: list[str]) -> dict[str, Any]:
    """['orb.n_features=1500', 'backend.concurrent=false'] -> {'orb.n_features': 1500, ...} (TOML values)."""
    out: dict[str, Any] = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq:
            raise ConfigError(f"--set {item!r}: expected section.key=value")
        try:
            out[key.strip()] = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = value.strip()  # a bare word: a string
    return out


class EmbeddedInputs:
    """The frames whose raw inputs the recording embeds, as a Dataset (plvo.data.dataset)."""

    name = "embedded"

    def __init__(self, path: Path, identity: dict[str, Any]):
        rows: dict[int, dict[str, Any]] = {}
        for chunk in open_rrd(path).stream().filter(content=["/inputs/**"]):
            batch = chunk.to_record_batch()
            frames = batch.column("frame").to_pylist()
            for name in ("png", "scan", "time"):
                if name in batch.schema.names:
                    for f, v in zip(frames, batch.column(name).to_pylist()):
                        rows.setdefault(int(f), {})[name] = v[0]
        self._rows = {f: r for f, r in sorted(rows.items()) if {"png", "scan", "time"} <= set(r)}
        self.sequence = str(identity.get("sequence", "embedded"))
        self.calib = calib_from_dict(json.loads(identity["calib"]))

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, i: int) -> Frame:
        f = self.frame_indices[i]
        r = self._rows[f]
        image, scan = decode_inputs(r["png"], r["scan"])
        return Frame(f, float(r["time"]), image, scan, self.calib, None)

    @property
    def frame_indices(self) -> tuple[int, ...]:
        return tuple(self._rows)

    @property
    def gt_T_world_cam(self):
        return None

    @property
    def times(self) -> np.ndarray:
        return np.array([self._rows[f]["time"] for f in self._rows])


def _identity(data: RrdData) -> dict[str, Any]:
    return {k.split(":", 1)[1]: v for k, v in data.properties.items() if k.startswith("plvo_dataset:")}


def open_inputs(path: Path, data: RrdData, root: Path | None) -> tuple[Any, str, list[str]]:
    """(dataset, where from, notes): files under `root`, else the embedded inputs, else the recorded root."""
    from plvo.data.registry import open_dataset

    ident = _identity(data)
    if not ident:
        raise RecordingError(f"{path}: the recording does not say which dataset it ran (made before plvo "
                             "recorded it); nothing to reproduce")
    if root is None and _entities(path):
        ds = EmbeddedInputs(path, ident)
        if len(ds):
            return ds, "the inputs embedded in the recording", []
    recorded_root = str(ident.get("root", ""))
    if root is None and ident.get("synthetic_town") in (True, "True", "true") and not Path(recorded_root).is_dir():
        from plvo_app.cmd_viz import _synthetic_town

        root = _synthetic_town()[0]  # the default town, generated here as it was there (the hashes check it)
    if root is None:
        if not recorded_root or not Path(recorded_root).is_dir():
            raise RecordingError(f"{path}: give --root DIR: the recording was made from {recorded_root or '?'}, "
                                 "not found here, and embeds no inputs (record with --embed-inputs A:B)")
        root = Path(recorded_root)
    frames = json.loads(ident["frames"]) if isinstance(ident.get("frames"), str) else ident.get("frames")
    ds = open_dataset(root, str(ident["sequence"]), list(frames))
    return ds, str(root), _check_calibration(ds, ident) + _check_hashes(ds, data)


def _check_calibration(ds, ident: dict[str, Any]) -> list[str]:
    """The calibration read now against the recorded one (the camera matrix, the image size, the lidar's and the
    camera's transforms), as the frames' files are checked by their hashes: a changed calibration file changes
    every depth prior, and the run departing from frame 0 should say why."""
    recorded = ident.get("calib")
    if recorded is None:
        return ["the recording holds no calibration: it cannot be checked"]
    old = json.loads(recorded) if isinstance(recorded, str) else recorded
    new = calib_to_dict(ds.calib)
    changed = []
    for key in ("K", "T_cam_velo", "T_cam0_cam", "width", "height", "lidar_elevation_offset_deg"):
        if key not in old:
            continue
        a, b = np.asarray(old[key], float), np.asarray(new[key], float)
        if a.shape != b.shape or not np.allclose(a, b, rtol=1e-9, atol=1e-12):
            diff = "" if a.shape != b.shape else f" (largest change {np.abs(a - b).max():.6g})"
            changed.append(f"{key}{diff}")
    if not changed:
        return ["calibration: as recorded"]
    return [f"calibration: differs from the one recorded ({', '.join(changed)}): a changed calibration file "
            "changes every depth prior"]


def _entities(path: Path) -> set[str]:
    try:
        return {c.entity_path for c in open_rrd(path).stream().filter(content=["/inputs/scan"])}
    except Exception:  # noqa: BLE001
        return set()


def _check_hashes(ds, data: RrdData) -> list[str]:
    frames = data.properties.get("plvo_inputs:frames")
    if frames is None:
        return ["the recording holds no input hashes: the inputs cannot be checked"]
    frames = json.loads(frames) if isinstance(frames, str) else _list(frames)
    named = data.properties.get("plvo_inputs:hash")
    if named is None:  # a recording made before the digests were named: sha256 prefixes
        algorithm, column = "sha256", "sha256"
    else:
        algorithm, column = str(_list(named)[0]), "hash"
    want = {int(f): (i, s) for f, i, s in zip(frames, _list(data.properties[f"plvo_inputs:image_{column}"]),
                                              _list(data.properties[f"plvo_inputs:scan_{column}"]))}
    bad = []
    for f, (image, scan) in input_files(ds).items():
        if f not in want:
            continue
        for kind, file, h in (("image", image, want[f][0]), ("scan", scan, want[f][1])):
            if not file_digest(file, algorithm).startswith(str(h)):
                bad.append(f"frame {f}: {kind} file {file} differs from the one recorded")
    bad += _changed_times(ds, data, frames)
    if not bad:
        return [f"inputs: all {2 * len(want)} files match the recorded hashes"]
    return bad[:5] + ([f"... and {len(bad) - 5} more input files differ"] if len(bad) > 5 else [])


def _changed_times(ds, data: RrdData, frames: list) -> list[str]:
    """The frames whose time (times.txt, a bag's stamps) differs from the recorded one: the motion model, the gap
    check and deskewing read them, so a changed time changes the run as a changed file does."""
    recorded = data.properties.get("plvo_inputs:times")
    if recorded is None:  # a recording made before the times were kept
        return []
    now = dict(zip(map(int, ds.frame_indices), np.asarray(ds.times, float)))
    return [f"frame {f}: its time {now[int(f)]:.6f} s differs from the one recorded ({float(t):.6f} s)"
            for f, t in zip(frames, _list(recorded)) if int(f) in now and abs(now[int(f)] - float(t)) > 1e-6]


def _list(v: Any) -> list:
    return v if isinstance(v, list) else [v]


def rerun_inputs(dataset, cfg: SystemConfig, out: Path) -> None:
    """Run `dataset` with `cfg`, recorded at the summary level to `out`."""
    from plvo.recording import RunInfo
    from plvo.runtime.system import System
    from plvo_app.recording_levels import DetailOptions
    from plvo_app.rerun_recorder import RerunOptions, RerunRecorder

    rec = RerunRecorder(out, RerunOptions(detail=DetailOptions(level="summary")))
    system = System(cfg, rec)
    system.start(RunInfo("reproduce", dataset.sequence, dataset.calib, tuple(dataset.frame_indices), None, {},
                         "", "", "plvo reproduce"))
    try:
        for i in range(len(dataset)):
            system.step(dataset[i])
        system.finish()
    finally:
        system.close()


def _poses(data: RrdData) -> dict[int, np.ndarray]:
    return {f: _pose_from_row(row) for f, row in data.rows("/world/camera")}


def _stage_values(data: RrdData) -> dict[str, dict[int, float]]:
    out: dict[str, dict[int, float]] = {}
    for entity in data.temporal:
        if entity.startswith("/metrics/") and not entity.startswith("/metrics/time/"):
            out[entity.removeprefix("/metrics/")] = {f: float(row["Scalars:scalars"][0])
                                                     for f, row in data.rows(entity) if row.get("Scalars:scalars")}
    decisions: dict[int, float] = {}
    for f, _, text in data.log:  # "frame F: keyframe K (reason)": the keyframe decision
        if text.startswith(f"frame {f}: keyframe "):
            decisions[f] = float(text.split()[3])
    out["keyframes/keyframe_id"] = decisions
    return out


def compare(old: RrdData, new: RrdData, tol_m: float, tol_deg: float, report: Report) -> None:
    a, b = _poses(old), _poses(new)
    frames = [f for f in report.frames if f in a and f in b]
    if frames and frames[0] != min(a):  # a fresh run from a later frame: its world is that frame's camera
        T0 = inv(a[frames[0]])
        a = {f: T0 @ T for f, T in a.items()}
    for f in frames:
        d = inv(a[f]) @ b[f]
        dm, ddeg = float(np.linalg.norm(a[f][:3, 3] - b[f][:3, 3])), float(np.degrees(rotation_angle(d)))
        report.max_diff = (max(report.max_diff[0], dm), max(report.max_diff[1], ddeg))
        if report.pose_frame is None and (dm > tol_m or ddeg > tol_deg):
            report.pose_frame, report.pose_diff = f, (dm, ddeg)
    sa, sb = _stage_values(old), _stage_values(new)
    partial = _ended_early(old)
    compared = set(report.frames) & set(a)  # a clip holds only its window: the frames before it are not compared
    changes: list[tuple[int, int, str]] = []
    for name in sorted(set(sa) | set(sb)):
        va, vb = sa.get(name, {}), sb.get(name, {})
        for f in sorted((set(va) | set(vb)) & compared):
            x, y = va.get(f), vb.get(f)
            if x is None and partial:  # the recorded run ended before writing it
                continue
            if x is None or y is None or abs(x - y) > 1e-9 * max(1.0, abs(x)):
                stage = KEYFRAME_CONSEQUENCES.get(name, name.split("/")[0])
                rank = STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER)
                changes.append((f, rank, f"{name} {_fmt(x)} -> {_fmt(y)}"))
                break
    if changes:
        f, _, what = min(changes)
        same_frame = sum(1 for c in changes if c[0] == f) - 1
        report.stage_frame, report.stage = f, what + (f" (and {same_frame} more at that frame)" if same_frame else "")


def _ended_early(data: RrdData) -> bool:
    """The recorded run was interrupted or failed: some stage results of its last frames were never written."""
    status = data.properties.get("plvo_run:status")
    status = _list(status)[0] if status is not None else "complete"
    return str(status) not in ("complete", "degraded")


def _fmt(v: float | None) -> str:
    return "absent" if v is None else f"{v:g}"


def reproduce(path: Path, root: Path | None = None, overrides: dict[str, Any] | None = None,
              tol_m: float = 0.01, tol_deg: float = 0.1, keep: Path | None = None) -> Report:
    old = read_rrd(path, content=COMPARED)
    cfg = recorded_config(old, overrides or {}, path)
    dataset, source, notes = open_inputs(path, old, root)
    if overrides:
        notes.append("config: the recorded one with " + ", ".join(f"{k} = {v!r}" for k, v in overrides.items()))
    if cfg.backend.concurrent:
        notes.append("note: the config runs the back end concurrently, so runs may differ from one another; "
                     "--set backend.concurrent=false for a deterministic rerun")
    recorded_frames = sorted(f for f, _ in old.rows("/world/camera"))
    frames = [f for f in dataset.frame_indices if not recorded_frames or f <= recorded_frames[-1]]
    if recorded_frames and frames and frames[0] != recorded_frames[0]:
        notes.append(f"the recorded run started at frame {recorded_frames[0]}: this is a fresh run from frame "
                     f"{frames[0]}, its poses compared after aligning at that frame")
    if not frames:
        raise RecordingError(f"{path}: none of the recorded frames is among the inputs")
    with tempfile.TemporaryDirectory(prefix="plvo-reproduce-") as tmp:
        out = keep or Path(tmp) / "rerun.rrd"
        rerun_inputs(_Prefix(dataset, len(frames)), cfg, out)
        new = read_rrd(out, content=COMPARED)
    if _ended_early(old):
        notes.append(f"the recorded run ended {_list(old.properties['plvo_run:status'])[0]}: the stage results it "
                     "never wrote are not compared")
    report = Report(source, frames, notes)
    compare(old, new, tol_m, tol_deg, report)
    return report


class _Prefix:
    """The first n frames of a dataset (an interrupted recording ran fewer than it names)."""

    def __init__(self, ds, n: int):
        self._ds, self._n = ds, n
        self.sequence, self.calib = ds.sequence, ds.calib

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i: int) -> Frame:
        return self._ds[i]

    @property
    def frame_indices(self) -> tuple[int, ...]:
        return tuple(self._ds.frame_indices[:self._n])
