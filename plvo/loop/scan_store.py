"""The loop database's scans, on disk: a verification registers the query's scan to the candidate's, so every
keyframe's scan must stay reachable, but it is read only for the few candidates verified.

Each compact scan (plvo.loop.closer.compact_scan: int16 centimetres, ~80 kB for a town scan) is appended to one
file in a private temporary folder and read back by offset. At KITTI 00's 1500 keyframes that is ~120 MB of file
(reclaimable page cache) instead of ~120 MB of the loop worker's resident memory. The folder goes when the store is
closed or collected, and with the process (it is unlinked right after opening where the OS allows).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np


class ScanStore:
    """Append-only (M,3) int16 scans by keyframe id, kept in an anonymous temporary file."""

    def __init__(self, folder: str | None = None) -> None:
        fd, path = tempfile.mkstemp(prefix="plvo-loop-scans-", dir=folder)
        self._file = os.fdopen(fd, "w+b")
        try:
            os.unlink(path)  # the open file stays readable; nothing is left behind by a killed process
        except OSError:
            self._path = path
        else:
            self._path = None
        self._where: dict[int, tuple[int, int]] = {}  # kf id -> (byte offset, rows)

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._where

    def put(self, kf_id: int, scan: np.ndarray) -> None:
        scan = np.ascontiguousarray(scan, dtype=np.int16).reshape(-1, 3)
        self._file.seek(0, os.SEEK_END)
        self._where[int(kf_id)] = (self._file.tell(), len(scan))
        self._file.write(scan.tobytes())

    def get(self, kf_id: int) -> np.ndarray | None:
        where = self._where.get(int(kf_id))
        if where is None:
            return None
        offset, rows = where
        self._file.flush()
        self._file.seek(offset)
        return np.frombuffer(self._file.read(rows * 6), np.int16).reshape(rows, 3)

    @property
    def bytes_on_disk(self) -> int:
        return sum(rows * 6 for _, rows in self._where.values())

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

    def __getstate__(self):
        raise TypeError("a ScanStore is the loop closer's own (an open file): it is not shipped between processes")
