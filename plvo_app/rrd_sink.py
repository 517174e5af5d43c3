"""Writing a .rrd from Python, so that a failed write is seen at once and the file stays readable.

Rerun's own file sink (`RecordingStream.save`) writes from a Rust thread: on a full disk it logs an error, the run
goes on, and the next flush blocks for ever; the file it leaves ends mid-message, which Rerun's reader refuses
whole. Here the stream's encoded bytes are taken from `RecordingStream.binary_stream()` once a step and written by
`RrdFileSink.pump`: the first failed write raises RecordingError, and the file is cut back to its last complete
message, which Rerun reads (as a file without a footer: "legacy", read by a whole-file scan).

RRD framing (re_log_encoding, RRF2): a 12-byte stream header ("RRF2", version, options), then messages of a
16-byte header (kind u64, payload length u64, little-endian) and the payload; kind 0 ends a stream (its payload is
the footer, followed by a trailer). Each `binary_stream().read()` returns a whole stream (header ... end): the
messages are copied, the headers after the first and the ends are dropped (a concatenation of streams with
footers fails Rerun's CRC check).
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path
from typing import Any

from plvo.errors import RecordingError

log = logging.getLogger(__name__)

STREAM_HEADER = 12
MESSAGE_HEADER = 16
END = 0


def message_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, stop) of each complete message of one encoded stream, up to its end marker."""
    spans, pos, end = [], STREAM_HEADER, len(data)
    while pos + MESSAGE_HEADER <= end:
        kind, length = struct.unpack_from("<QQ", data, pos)
        if kind == END or pos + MESSAGE_HEADER + length > end:
            break
        spans.append((pos, pos + MESSAGE_HEADER + length))
        pos += MESSAGE_HEADER + length
    return spans


def messages(data: bytes) -> tuple[bytes, bytes]:
    """(stream header, the complete messages before the end marker) of one encoded stream."""
    spans = message_spans(data)
    return data[:STREAM_HEADER], data[STREAM_HEADER:spans[-1][1] if spans else STREAM_HEADER]


def complete_prefix(path: str | Path) -> int:
    """Bytes of `path` up to the end of its last complete message (0 when not even the header is there)."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < STREAM_HEADER or not data.startswith(b"RRF"):
        return 0
    header, body = messages(data)
    return len(header) + len(body)


class RrdFileSink:
    """Streams `rec` into a new file `path` (never an existing one); `pump()` once a step, `close()` at the end."""

    def __init__(self, rec: Any, path: str | Path, default_blueprint: Any = None):
        self.path = Path(path)
        self.rec = rec
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "xb", buffering=0)  # unbuffered: a failed write raises in write()
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot write the recording ({exc.strerror or exc})") from None
        self._stream = rec.binary_stream()
        if default_blueprint is not None:
            rec.send_blueprint(default_blueprint, make_active=False, make_default=True)
        self.written = 0  # bytes on disk, all of them complete messages
        self.failed: str | None = None

    def pump(self, flush: bool = False) -> None:
        """Write what the stream has encoded so far (flush: first wait for everything logged to be encoded)."""
        if self.failed is not None or self._file.closed:
            return
        data = self._stream.read(flush=flush)
        if not data:
            return
        if self.written == 0:
            self._write(data[:STREAM_HEADER])
        view = memoryview(data)
        for start, stop in message_spans(data):  # one by one: a full disk keeps every message that fitted
            self._write(view[start:stop])

    def _write(self, data: bytes | memoryview) -> None:
        view = memoryview(data)
        try:
            while view:
                n = self._file.write(view)
                view = view[n:]
        except OSError as exc:
            self._fail(exc)
        self.written += len(data)

    def _fail(self, exc: OSError) -> None:
        self.failed = exc.strerror or str(exc)
        try:  # cut the half-written message off: what was complete stays readable
            self._file.truncate(self.written)
        except OSError:
            log.exception("%s: cannot cut the recording back to %d bytes", self.path, self.written)
        finally:
            self._close_file()
        raise RecordingError(f"{self.path}: writing the recording failed ({self.failed}); the {self.written} "
                             "bytes written before are kept, readable")

    def _close_file(self) -> None:
        try:
            self._file.close()
        except OSError:
            pass

    def close(self) -> None:
        """Write the rest and close the file. After a failed write only the file is closed (no second error)."""
        if self._file.closed:
            return
        try:
            self.rec.disconnect()  # ends the stream: everything logged is encoded
            self.pump(flush=False)
        finally:
            self._close_file()
        if self.written == 0:
            os.unlink(self.path)  # an empty file would look like a recording
