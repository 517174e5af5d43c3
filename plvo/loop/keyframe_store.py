"""The loop database's keyframes, on disk: a verification matches the query against a candidate's features with
depth and registers their scans, so every keyframe's must stay reachable, but it is read only for the few
candidates verified.

Each keyframe, compacted (plvo.loop.closer.compact_keyframe: features with depth in float32, ~25 kB; the scan as
int16 centimetres, ~80 kB for a town scan), is appended to one file in a private temporary folder and read back by
offset. At KITTI 00's 1500 keyframes that is ~160 MB of file (reclaimable page cache) instead of ~160 MB of the loop
worker's resident memory; what stays in memory is an offset a keyframe. The folder goes when the store is closed or
collected, and with the process (it is unlinked right after opening where the OS allows).
"""

from __future__ import annotations

import os
import tempfile
from typing import Any, NoReturn

import numpy as np

# What a keyframe's record holds, in order: (name, dtype, trailing shape); the row counts are kept in memory.
_FIELDS = (("T_world_cam", np.float64, (4, 4)), ("keypoints", np.float32, (2,)), ("descriptors", np.uint8, (32,)),
           ("points_cam", np.float32, (3,)), ("segments", np.float32, (4,)), ("line_descriptors", np.uint8, (32,)),
           ("lines_cam", np.float32, (2, 3)), ("scan", np.int16, (3,)))
FIELD_NAMES = tuple(name for name, _, _ in _FIELDS)


class KeyframeStore:
    """Append-only keyframe records (named arrays, see _FIELDS) by keyframe id, kept in an anonymous temporary
    file."""

    def __init__(self, folder: str | None = None) -> None:
        fd, path = tempfile.mkstemp(prefix="plvo-loop-keyframes-", dir=folder)
        self._file = os.fdopen(fd, "w+b")
        self._path: str | None
        try:
            os.unlink(path)  # the open file stays readable; nothing is left behind by a killed process
        except OSError:
            self._path = path
        else:
            self._path = None
        # kf id -> (byte offset, frame index, rows of each field; -1 for an absent scan)
        self._where: dict[int, tuple[int, int, tuple[int, ...]]] = {}
        self.bytes_on_disk = 0

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._where

    def put(self, kf_id: int, arrays: dict[str, np.ndarray | None], frame_index: int = -1) -> None:
        """Append keyframe kf_id's arrays (every name of _FIELDS; the scan may be None)."""
        self._file.seek(0, os.SEEK_END)
        offset, rows, parts = self._file.tell(), [], []
        for name, dtype, shape in _FIELDS:
            a = arrays[name]
            if a is None:
                rows.append(-1)
                continue
            a = np.ascontiguousarray(a, dtype=dtype).reshape(-1, *shape)
            rows.append(len(a) if name != "T_world_cam" else 1)
            parts.append(a.tobytes())
        data = b"".join(parts)
        self._file.write(data)
        self.bytes_on_disk += len(data)
        self._where[int(kf_id)] = (offset, int(frame_index), tuple(rows))

    def get(self, kf_id: int) -> tuple[dict[str, Any], int] | None:
        """Keyframe kf_id's arrays and frame index as put (in the store's dtypes), or None when absent."""
        where = self._where.get(int(kf_id))
        if where is None:
            return None
        offset, frame_index, rows = where
        sizes = [0 if n < 0 else n * int(np.prod(shape)) * np.dtype(dt).itemsize
                 for (_, dt, shape), n in zip(_FIELDS, rows)]
        self._file.flush()
        self._file.seek(offset)
        data = bytearray(self._file.read(sum(sizes)))  # writeable arrays, as the keyframe was given
        out: dict[str, Any] = {}  # field -> array, None for an absent one
        at = 0
        for (name, dtype, shape), n, size in zip(_FIELDS, rows, sizes):
            out[name] = None if n < 0 else np.frombuffer(data, dtype, n * int(np.prod(shape)), at).reshape(n, *shape)
            at += size
        T = out["T_world_cam"]
        assert T is not None  # every keyframe has a pose
        out["T_world_cam"] = T[0]
        return out, frame_index

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
        if self._path is not None:
            try:
                os.unlink(self._path)
            except OSError:
                pass
            self._path = None

    def __del__(self) -> None:
        self.close()

    def __getstate__(self) -> NoReturn:
        raise TypeError("a KeyframeStore is the loop closer's own (an open file): it is not shipped between "
                        "processes")
