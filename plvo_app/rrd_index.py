"""A .rrd indexed for replay: its chunks kept as Arrow (as read, never turned into Python lists), an index per
(entity, component) of the frames that have it, and each layer's value decoded only when a frame asks for it
(with a small cache). Opening a whole-sequence recording costs one pass of Rerun's reader, memory about the size
of the file, and a frame change decodes a handful of rows.

`IndexedSceneStore` answers the viewer as a SceneStore does (frames, latest, count, name, K, gt, ...), from the
index; `load_rrd` returns one. The scan and the image come from whichever is later of the full one (detail frames)
and the keyframe's thin one (every keyframe, every level), the full one at a frame that has both; `detail` lists the
frames with full detail and why.
"""

from __future__ import annotations

import bisect
import json
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from plvo.errors import RecordingError
from plvo_app.rrd_reader import read_chunks
from plvo_app.scene_common import ORANGE, depth_colors, depth_image_points

_TIMES = {"rerun.controls.RowId", "frame", "log_time", "sensor_time"}
CLEAR = "Clear:is_recursive"
EMPTIED = "#emptied"  # index key suffix: rows where a component was logged empty


class RrdIndex:
    """entity -> component -> (sorted frames, (batch, row) per frame); later rows of a frame win (row ids grow
    with logging order). Static values and the recording properties are decoded up front (they are small)."""

    def __init__(self, path: str | Path):
        p = Path(path)
        if not p.is_file():
            raise RecordingError(f"{p}: no such recording file")
        chunks = read_chunks(p)  # a file cut short gives its complete part
        self.static: dict[str, dict[str, Any]] = {}
        self.properties: dict[str, Any] = {}
        self.batches: list[pa.RecordBatch] = []
        rows: dict[tuple[str, str], list[tuple[int, bytes, int, int]]] = {}
        frames: set[int] = set()
        for chunk in chunks:
            batch, entity = chunk.to_record_batch(), chunk.entity_path
            names = [n for n in batch.schema.names if n not in _TIMES]
            if entity.startswith("/__properties"):
                group = entity.removeprefix("/__properties").strip("/") or "recording"
                for n in names:
                    v = batch.column(n)[-1].as_py()
                    self.properties[f"{group}:{n}"] = v[0] if isinstance(v, list) and len(v) == 1 else v
                continue
            if chunk.is_static:
                target = self.static.setdefault(entity, {})
                for n in names:
                    v = batch.column(n)[-1].as_py()
                    if v is not None:
                        target[n] = v
                continue
            if "frame" not in batch.schema.names:
                continue
            bi = len(self.batches)
            self.batches.append(batch)
            fr = batch.column("frame").to_numpy(zero_copy_only=False)
            ids = batch.column("rerun.controls.RowId").to_pylist()
            frames.update(int(f) for f in np.unique(fr))
            for n in names:
                col = batch.column(n)
                valid = col.is_valid().to_numpy(zero_copy_only=False)
                if pa.types.is_list(col.type):  # an empty list is a cleared component (e.g. EncodedImage.cleared())
                    empty = pc.fill_null(pc.equal(pc.list_value_length(col), 0), False).to_numpy(zero_copy_only=False)
                    emptied = rows.setdefault((entity, n + EMPTIED), [])
                    emptied += [(int(fr[r]), ids[r], bi, r) for r in np.flatnonzero(valid & empty)]
                    valid = valid & ~empty
                dest = rows.setdefault((entity, n), [])
                dest += [(int(fr[r]), ids[r], bi, r) for r in np.flatnonzero(valid)]
        self.frames = sorted(frames)
        self._index: dict[tuple[str, str], tuple[list[int], list[tuple[int, int]]]] = {}
        self._last_id: dict[tuple[str, str], dict[int, bytes]] = {}  # row id of each frame's latest row
        for key, rs in rows.items():
            rs.sort(key=lambda r: (r[0], r[1]))
            last: dict[int, tuple[int, int]] = {}
            ids_of: dict[int, bytes] = {}
            for f, rid, bi, r in rs:  # the latest row of each frame
                last[f], ids_of[f] = (bi, r), rid
            fs = sorted(last)
            self._index[key] = (fs, [last[f] for f in fs])
            self._last_id[key] = ids_of

    def frames_of(self, entity: str, component: str) -> list[int]:
        return self._index.get((entity, component), ([], []))[0]

    def latest(self, entity: str, component: str, frame: int) -> tuple[int, int, int] | None:
        """(frame, batch, row) of the latest `component` of `entity` at or before `frame`, or None (also when a
        Clear of the entity came after it)."""
        fs, where = self._index.get((entity, component), ([], []))
        i = bisect.bisect_right(fs, frame)
        if not i:
            return None
        f = fs[i - 1]
        data_id = self._last_id[(entity, component)][f]
        for key in ((entity, CLEAR), (entity, component + EMPTIED)):
            cleared = self._index.get(key, ([], []))[0]
            j = bisect.bisect_right(cleared, frame)
            # a clear after the data, or at its frame but logged later (held-back detail is logged after the clear)
            if j and (cleared[j - 1] > f or (cleared[j - 1] == f and self._last_id[key][f] > data_id)):
                return None
        return (f, *where[i - 1])

    def value(self, batch: int, row: int, component: str) -> pa.Array:
        """The component's batch of one row (an Arrow list's values)."""
        return self.batches[batch].column(component)[row].values


def _points(a: pa.Array) -> np.ndarray:
    """list of fixed_size_list<float,3> -> (N,3) float32."""
    return a.flatten().to_numpy(zero_copy_only=False).astype(np.float32).reshape(-1, 3)


def _segments(a: pa.Array) -> np.ndarray:
    """strips of two points each -> (M,2,3) float32."""
    return a.flatten().flatten().to_numpy(zero_copy_only=False).astype(np.float32).reshape(-1, 2, 3)


def _colors(a: pa.Array) -> np.ndarray:
    c = a.to_numpy(zero_copy_only=False).astype(np.uint32)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], axis=1).astype(np.uint8)


def _pose(idx: RrdIndex, entity: str, frame: int) -> np.ndarray | None:
    t = idx.latest(entity, "Transform3D:translation", frame)
    if t is None:
        return None
    T = np.eye(4)
    T[:3, 3] = idx.value(t[1], t[2], "Transform3D:translation").flatten().to_numpy(zero_copy_only=False)
    m = idx.latest(entity, "Transform3D:mat3x3", frame)
    if m is not None:  # Rerun stores column-major
        T[:3, :3] = idx.value(m[1], m[2], "Transform3D:mat3x3").flatten().to_numpy(
            zero_copy_only=False).reshape(3, 3).T
    return T


def _blob(idx: RrdIndex, b: int, r: int, component: str) -> bytes:
    blob = idx.value(b, r, component)[0]
    return blob.as_py() if isinstance(blob, pa.BinaryScalar) else blob.values.to_numpy().tobytes()


def _static_matrix(values: dict[str, Any], component: str) -> np.ndarray | None:
    v = values.get(component)
    return None if not v else np.asarray(v[0], float).reshape(3, 3).T  # Rerun stores column-major


THIN_SCAN = "/world/lidar/thin"
# layer -> (entity, the component whose frames say when the layer changes)
LAYER_SOURCES = {
    "pose": ("/world/camera", "Transform3D:translation"),
    "image": ("/world/camera/image", "EncodedImage:blob"),
    "scan": ("/world/lidar/scan", "Points3D:positions"),
    "map_points": ("/world/map/points", "Points3D:positions"),
    "map_lines": ("/world/map/lines", "LineStrips3D:strips"),
    "keyframes": ("/world/keyframes", "Points3D:positions"),
    "graph": ("/world/graph", "LineStrips3D:strips"),
    "loops": ("/world/loops", "LineStrips3D:strips"),
    "est": ("/world/trajectory/est", "LineStrips3D:strips"),
    "log": ("/log", "TextLog:text"),
}
# layer -> its thin variant (written on every keyframe at every level), shown where it is later than the full one
THIN_SOURCES = {
    "image": ("/world/camera/image/keyframe", "EncodedImage:blob"),
    "scan": (f"{THIN_SCAN}/0", "EncodedDepthImage:blob"),
}


class IndexedSceneStore:
    """A SceneStore over an RrdIndex: the same layers and latest-at answers, decoded per frame on demand."""

    def __init__(self, path: str | Path, cache_size: int = 64):
        self.index = idx = RrdIndex(path)
        self.frames = idx.frames
        self.name = str(idx.properties.get("plvo:sequence", Path(path).stem))
        self.lock = threading.RLock()
        self._cache: OrderedDict[tuple, Any] = OrderedDict()
        self._cache_size = cache_size
        self.K, self.width, self.height, self.gt = None, 0, 0, None
        pin = idx.static.get("/world/camera/image", {})
        if "Pinhole:image_from_camera" in pin:
            self.K = np.asarray(pin["Pinhole:image_from_camera"][0], float).reshape(3, 3).T  # column-major
            self.width, self.height = (int(v) for v in pin["Pinhole:resolution"][0])
        gt = idx.static.get("/world/trajectory/gt", {}).get("LineStrips3D:strips")
        if gt:
            self.gt = np.asarray(gt[0], np.float32)
        self.detail = self._detail_windows()
        self._track: tuple[list[int], np.ndarray] | None = None

    def _detail_windows(self) -> list[tuple[int, int, str]]:
        """[first, end) frames with full detail and why: the recording's list (written on close), else (a recording
        cut short, or older than the list) the runs of frames that hold the full image."""
        listed = self.index.properties.get("plvo_detail:windows")
        if listed:  # within the frames there are (a clip of a recording keeps its properties)
            first, end = (self.frames[0], self.frames[-1] + 1) if self.frames else (0, 0)
            return [(max(int(a), first), min(int(b), end), str(why)) for a, b, why in json.loads(listed)
                    if int(a) < end and int(b) > first]
        runs: list[tuple[int, int, str]] = []
        for f in self.index.frames_of(*LAYER_SOURCES["image"]):
            if runs and runs[-1][1] == f:
                runs[-1] = (runs[-1][0], f + 1, runs[-1][2])
            else:
                runs.append((f, f + 1, "full detail (the recording has no list of why)"))
        return runs

    def track(self, after: int, upto: int) -> np.ndarray:
        """(N,3) float32 camera positions of the frames in (after, upto]: the way the car went since the estimate
        was last drawn (the summary redraws it every 20 keyframes; the camera pose is there every frame)."""
        with self.lock:
            if self._track is None:  # every frame's position, decoded once: 4541 frames in ~55 kB
                frames, where = self.index._index.get(LAYER_SOURCES["pose"], ([], []))
                pos = np.zeros((len(frames), 3), np.float32)
                by_batch: dict[int, list[int]] = {}
                for i, (b, _) in enumerate(where):
                    by_batch.setdefault(b, []).append(i)
                for b, rows in by_batch.items():
                    col = self.index.batches[b].column(LAYER_SOURCES["pose"][1])
                    picked = col.take(pa.array([where[i][1] for i in rows]))  # one translation a row
                    pos[rows] = picked.flatten().flatten().to_numpy(zero_copy_only=False).reshape(-1, 3)
                self._track = (frames, pos)
            frames, pos = self._track
        return pos[bisect.bisect_right(frames, after):bisect.bisect_right(frames, upto)]

    def count(self, layer: str) -> int:
        """Frames at which `layer` changes (its full or its thin variant)."""
        if layer not in LAYER_SOURCES:
            return 0
        frames = set(self.index.frames_of(*LAYER_SOURCES[layer]))
        if layer in THIN_SOURCES:
            frames |= set(self.index.frames_of(*THIN_SOURCES[layer]))
        return len(frames)

    def source(self, layer: str, frame_index: int) -> tuple[str, int] | None:
        """("full" or "thin", the frame it is from) of what `latest` shows of `layer` at `frame_index`, or None."""
        hit = self._hit(layer, frame_index)
        return None if hit is None else (hit[0], hit[2][0])

    def _hit(self, layer: str, frame_index: int) -> tuple[str, str, tuple[int, int, int]] | None:
        """(variant, entity, (frame, batch, row)): the full one unless the thin one is from a later frame."""
        if layer not in LAYER_SOURCES:
            return None
        entity, component = LAYER_SOURCES[layer]
        hit = self.index.latest(entity, component, frame_index)
        if layer in THIN_SOURCES:
            thin_entity, thin_component = THIN_SOURCES[layer]
            thin = self.index.latest(thin_entity, thin_component, frame_index)
            if thin is not None and (hit is None or thin[0] > hit[0]):
                return "thin", thin_entity, thin
        return None if hit is None else ("full", entity, hit)

    def latest(self, layer: str, frame_index: int) -> Any:
        found = self._hit(layer, frame_index)
        if found is None:
            return None
        variant, entity, hit = found
        key = (layer, variant, hit[0])
        with self.lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
            value = self._decode_thin(layer, hit) if variant == "thin" else self._decode(layer, entity, hit)
            self._cache[key] = value
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
            return value

    def _decode_thin(self, layer: str, hit: tuple[int, int, int]) -> Any:
        idx, (f, b, r) = self.index, hit
        if layer == "image":
            return _blob(idx, b, r, THIN_SOURCES["image"][1])
        # the scan: each face's depth image back to points (its static pinhole and turn), into the world
        parts = []
        k = 0
        while (entity := f"{THIN_SCAN}/{k}") in idx.static:
            k += 1
            st = idx.static[entity]
            K, R = _static_matrix(st, "Pinhole:image_from_camera"), _static_matrix(st, "Transform3D:mat3x3")
            at = idx.latest(entity, "EncodedDepthImage:blob", f)
            if K is None or at is None or at[0] != f:
                continue
            meter = float((st.get("EncodedDepthImage:meter") or [1000.0])[0])
            pts = depth_image_points(_blob(idx, at[1], at[2], "EncodedDepthImage:blob"), K, meter)
            parts.append(pts if R is None else pts @ R.T)
        velo = np.concatenate(parts) if parts else np.zeros((0, 3))
        T = _pose(idx, "/world/lidar", f)
        T = np.eye(4) if T is None else T
        return (velo @ T[:3, :3].T + T[:3, 3]).astype(np.float32), depth_colors(np.linalg.norm(velo, axis=1))

    def _decode(self, layer: str, entity: str, hit: tuple[int, int, int]) -> Any:
        idx, (f, b, r) = self.index, hit
        if layer == "pose":
            return _pose(idx, entity, f)
        if layer == "image":
            return _blob(idx, b, r, "EncodedImage:blob")
        if layer == "log":
            return str(idx.value(b, r, "TextLog:text")[0].as_py())
        if layer == "scan":
            pts = _points(idx.value(b, r, "Points3D:positions")).astype(np.float64)
            c = idx.latest(entity, "Points3D:colors", f)
            colors = _colors(idx.value(c[1], c[2], "Points3D:colors")) if c is not None and c[0] == f else None
            if colors is None or len(colors) != len(pts):
                colors = np.full((len(pts), 3), 200, np.uint8)
            T = _pose(idx, "/world/lidar", f)
            T = np.eye(4) if T is None else T
            return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32), colors
        if layer in ("map_points", "keyframes"):
            return _points(idx.value(b, r, "Points3D:positions"))
        if layer in ("map_lines", "loops"):
            return _segments(idx.value(b, r, "LineStrips3D:strips"))
        if layer == "graph":
            segs = _segments(idx.value(b, r, "LineStrips3D:strips"))
            c = idx.latest(entity, "LineStrips3D:colors", f)
            colors = _colors(idx.value(c[1], c[2], "LineStrips3D:colors")) if c is not None else None
            if colors is None or len(colors) != len(segs):
                colors = np.tile(np.array(ORANGE, np.uint8), (len(segs), 1))
            return segs, colors
        if layer == "est":
            return _points(idx.value(b, r, "LineStrips3D:strips").flatten())
        raise KeyError(layer)


def load_rrd(path: str | Path) -> IndexedSceneStore:
    """A plvo .rrd (also one cut short by Ctrl-C) as the viewer's store: indexed, decoded per frame on demand, so a
    whole sequence opens in seconds in memory about its size."""
    return IndexedSceneStore(path)
