"""A .rrd indexed for replay: its chunks kept as Arrow (as read, never turned into Python lists), an index per
(entity, component) of the frames that have it, and each layer's value decoded only when a frame asks for it
(with a small cache). Opening a whole-sequence recording costs one pass of Rerun's reader, memory about the size
of the file, and a frame change decodes a handful of rows.

`IndexedSceneStore` answers the viewer as a SceneStore does (frames, latest, count, name, K, gt, ...), from the
index; `load_rrd` returns one.
"""

from __future__ import annotations

import bisect
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from plvo.errors import RecordingError
from plvo_app.rrd_reader import read_chunks
from plvo_app.scene_common import ORANGE

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

    def count(self, layer: str) -> int:
        return len(self.index.frames_of(*LAYER_SOURCES[layer])) if layer in LAYER_SOURCES else 0

    def latest(self, layer: str, frame_index: int) -> Any:
        if layer not in LAYER_SOURCES:
            return None
        entity, component = LAYER_SOURCES[layer]
        hit = self.index.latest(entity, component, frame_index)
        if hit is None:
            return None
        key = (layer, hit[0])
        with self.lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
            value = self._decode(layer, entity, hit)
            self._cache[key] = value
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
            return value

    def _decode(self, layer: str, entity: str, hit: tuple[int, int, int]) -> Any:
        idx, (f, b, r) = self.index, hit
        if layer == "pose":
            return _pose(idx, entity, f)
        if layer == "image":
            blob = idx.value(b, r, "EncodedImage:blob")[0]
            return blob.as_py() if isinstance(blob, pa.BinaryScalar) else blob.values.to_numpy().tobytes()
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
