"""Read a .rrd back with rerun's chunk reader: per entity, the rows on the `frame` timeline, the static data and the
recording properties. Used by the viser replay and the tests; works on recordings cut short by Ctrl-C.
"""

from __future__ import annotations

import logging
import tempfile
import warnings
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rerun as rr

from plvo.errors import RecordingError
from plvo_app.rrd_sink import complete_prefix

log = logging.getLogger(__name__)
_SKIP = {"rerun.controls.RowId", "frame", "log_time", "sensor_time"}


@dataclass
class RrdData:
    """static: entity -> component -> value (a list, one item per instance batch).
    temporal: entity -> frame -> component -> value, later rows of a frame overriding earlier ones.
    sensor_time: frame -> seconds. properties: "group:name" -> value, e.g. "plvo:git_revision".
    log: every TextLog row of the `log` entity in logging order, as (frame, level, text): several a frame, which the
    latest-at view of `temporal` would fold into one.
    cleared: entity -> frames where a Clear ends its detail (the recording level stopped writing it)."""

    static: dict[str, dict[str, Any]] = field(default_factory=dict)
    temporal: dict[str, dict[int, dict[str, Any]]] = field(default_factory=lambda: defaultdict(dict))
    sensor_time: dict[int, float] = field(default_factory=dict)
    properties: dict[str, Any] = field(default_factory=dict)
    log: list[tuple[int, str, str]] = field(default_factory=list)
    cleared: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))

    def frames(self, entity: str | None = None) -> list[int]:
        """Sorted frame numbers with data (on `entity`, or on any entity)."""
        if entity is not None:
            return sorted(self.temporal.get(entity, {}))
        return sorted({f for rows in self.temporal.values() for f in rows})

    def rows(self, entity: str) -> Iterator[tuple[int, dict[str, Any]]]:
        """(frame, components) of `entity` in frame order."""
        rows = self.temporal.get(entity, {})
        for f in sorted(rows):
            yield f, rows[f]

    @property
    def entities(self) -> set[str]:
        return set(self.static) | set(self.temporal)


def read_rrd(path: str | Path, content: list[str] | None = None) -> RrdData:
    """Load every chunk of the first recording in `path` (only the entities matching the `content` filter
    expressions, e.g. ["/metrics/**", "/log"], when given; the properties always)."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording file")
    chunks = read_chunks(p, content)
    out = RrdData()
    pending: list[tuple[bytes, str, int, dict[str, Any]]] = []  # (row id, entity, frame, components)
    for chunk in chunks:
        batch = chunk.to_record_batch()
        entity = chunk.entity_path
        cols = {name: batch.column(name).to_pylist() for name in batch.schema.names if name not in _SKIP}
        if entity.startswith("/__properties"):
            group = entity.removeprefix("/__properties").strip("/") or "recording"
            for name, values in cols.items():
                value = values[-1]
                out.properties[f"{group}:{name}"] = value[0] if isinstance(value, list) and len(value) == 1 else value
            continue
        if chunk.is_static:
            target = out.static.setdefault(entity, {})
            for name, values in cols.items():
                if values[-1] is not None:
                    target[name] = values[-1]
            continue
        if "frame" not in batch.schema.names:
            continue
        frames = batch.column("frame").to_pylist()
        row_ids = batch.column("rerun.controls.RowId").to_pylist()
        times = batch.column("sensor_time").to_pylist() if "sensor_time" in batch.schema.names else None
        for i, f in enumerate(frames):
            pending.append((row_ids[i], entity, int(f), {k: v[i] for k, v in cols.items() if v[i] is not None}))
            if times is not None and times[i] is not None:
                out.sensor_time[int(f)] = _seconds(times[i])
    for _, entity, f, components in sorted(pending, key=lambda r: r[0]):  # row ids grow with logging order
        if set(components) == {"Clear:is_recursive"} or (components and all(v == [] for v in components.values())):
            out.cleared[entity].append(f)
            continue
        out.temporal[entity].setdefault(f, {}).update(components)
        if entity == "/log" and components.get("TextLog:text"):
            level = components.get("TextLog:level") or ["INFO"]
            out.log.append((f, str(level[0]), str(components["TextLog:text"][0])))
    return out


def read_chunks(path: str | Path, content: list[str] | None = None) -> list:
    """The chunks of a recording (of the `content` entities and the properties, when given); a file cut short
    mid-message (a process killed while writing) gives its complete part, with a warning."""
    p = Path(path)
    try:
        return _read_chunks(p, content)
    except Exception as exc:  # noqa: BLE001 - the bindings raise several types for a bad file
        return _read_cut_short(p, exc, content)


def open_rrd(path: str | Path):
    """Rerun's reader of a .rrd, without its warning about the footer plvo's files do not have (a user would read it
    at the end of every run): plvo_app/rrd_sink.py writes none, and Rerun then scans the whole file."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        return rr.chunk.RrdReader(str(path))


def _read_chunks(p: Path, content: list[str] | None = None) -> list:
    """The chunks of the recording (those of the `content` entities and the properties, when given)."""
    stream = open_rrd(p).stream()
    if content is not None:
        stream = stream.filter(content=[*content, "/__properties/**"])
    return list(stream)


def _read_cut_short(p: Path, exc: Exception, content: list[str] | None = None) -> list:
    """A recording whose last message is cut off (a process killed mid-write): read its complete messages."""
    size, keep = p.stat().st_size, complete_prefix(p)
    if not 0 < keep < size:
        raise RecordingError(f"{p}: not a readable Rerun recording ({exc})") from None
    with tempfile.TemporaryDirectory(prefix="plvo-rrd-") as tmp:
        copy = Path(tmp) / p.name
        with open(p, "rb") as src, open(copy, "wb") as dst:
            dst.write(src.read(keep))
        log.warning("%s: cut short after %d of %d bytes; reading its complete part", p, keep, size)
        try:
            return _read_chunks(copy, content)
        except Exception as exc2:  # noqa: BLE001
            raise RecordingError(f"{p}: not a readable Rerun recording ({exc2})") from None


def _seconds(value: Any) -> float:
    if hasattr(value, "total_seconds"):
        return float(value.total_seconds())
    return float(value) * 1e-9
