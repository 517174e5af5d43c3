"""Growable numpy columns, and landmark tables whose rows can be dropped while their ids stay valid."""

from __future__ import annotations

import numpy as np
from numpy.typing import DTypeLike

# column name -> (shape of one row, dtype, fill value of an empty row)
Spec = dict[str, tuple[tuple[int, ...], DTypeLike, object]]


class Columns:
    """Named numpy columns that grow together, by half again when full; rows [0, n) are in use."""

    def __init__(self, spec: Spec):
        self._spec = spec
        self.n = 0
        self.cols = {k: np.full((16, *shape), fill, dtype=dt) for k, (shape, dt, fill) in spec.items()}

    def append(self, **values: np.ndarray) -> np.ndarray:
        """Append k rows (every value (k, ...)); returns their row indices."""
        k = len(next(iter(values.values())))
        if self.n + k > self.capacity:
            self._resize(max(self.capacity + self.capacity // 2, self.n + k))
        rows = np.arange(self.n, self.n + k)
        for name in self._spec:
            if name in values:
                self.cols[name][rows] = values[name]
        self.n += k
        return rows

    @property
    def capacity(self) -> int:
        return len(next(iter(self.cols.values())))

    def keep(self, mask: np.ndarray) -> None:
        """Keep the rows where mask (n,) is True, in order; the capacity shrinks to a quarter more than is kept,
        so that memory follows what the table holds rather than the most it ever held."""
        kept = int(np.count_nonzero(mask))
        self._resize(16 + kept + kept // 4, mask)

    def _resize(self, capacity: int, mask: np.ndarray | None = None) -> None:
        """New arrays of `capacity` rows (callers keep it at 16 or more: row 0 always exists) holding rows [0, n), or
        only those where mask (n,) is True; n follows."""
        n = self.n if mask is None else int(np.count_nonzero(mask))
        for name, (shape, dt, fill) in self._spec.items():
            old = self.cols[name][: self.n]
            grown = np.full((capacity, *shape), fill, dtype=dt)
            if mask is None:
                grown[:n] = old
            else:
                np.compress(mask, old, axis=0, out=grown[:n])
            grown.flags.writeable = old.flags.writeable
            self.cols[name] = grown
        self.n = n

    def nbytes(self) -> int:
        return sum(c.nbytes for c in self.cols.values())

    def __getitem__(self, name: str) -> np.ndarray:
        return self.cols[name][: self.n]


class LandmarkTable(Columns):
    """Columns of landmarks keyed by id: ids are handed out in increasing order and never reused, and rows stay
    sorted by id when some are dropped (`keep`), so an id's row is found by binary search and an id handed to a
    worker stays valid (found or known gone) whatever was dropped meanwhile."""

    def __init__(self, spec: Spec):
        super().__init__({"id": ((), np.int64, -1), **spec})
        self.next_id = 0

    def append(self, **values: np.ndarray) -> np.ndarray:
        """Append k landmarks; returns their new ids."""
        k = len(next(iter(values.values())))
        ids = np.arange(self.next_id, self.next_id + k, dtype=np.int64)
        self.next_id += k
        super().append(id=ids, **values)
        return ids

    def rows(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k,) ids -> (k,) rows and (k,) bool found. A row where not found is 0: it indexes `cols` (whose capacity
        is at least 16) even in an empty table, and what it reads there must not be used."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        have = self["id"]
        if len(have) == 0:
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        rows = np.minimum(np.searchsorted(have, ids), len(have) - 1)
        found = have[rows] == ids
        return np.where(found, rows, 0), found

    def live_rows(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like rows, with found only where the landmark is also alive."""
        rows, found = self.rows(ids)
        return rows, found & self.cols["alive"][rows]
