"""Writing a .rrd from Python, so that a failed write is seen at once and the file stays readable.

Rerun's own file sink (`RecordingStream.save`) writes from a Rust thread: on a full disk it logs an error, the run
goes on, and the next flush blocks for ever; the file it leaves ends mid-message, which Rerun's reader refuses
whole. Here the stream's encoded bytes are taken from `RecordingStream.binary_stream()` and written by a Python
thread: the first failed write is raised as a RecordingError by `RrdFileSink.pump` at the next step (or by close),
and the file is cut back to its last complete message, which Rerun reads (as a file without a footer: "legacy",
read by a whole-file scan). The files have no footer (chunk manifest) even when complete: still valid RRD, read by
`plvo view`, the Rerun viewer and `rerun rrd print`; `rerun rrd verify` reports the missing footer and
`rerun rrd optimize FILE.rrd > OUT.rrd` writes one (Rerun's own docs for `save(write_footer=False)`).

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
import threading
from pathlib import Path
from typing import Any

from plvo.errors import RecordingError

log = logging.getLogger(__name__)

STREAM_HEADER = 12
MESSAGE_HEADER = 16
END = 0
WRITE_INTERVAL_S = 0.2  # the batcher hands chunks over every 2 s (plvo_app/rerun_recorder.py); checked 10x as often
# How long close() waits for the writer thread's last write: a write blocked that long (a hung network disk) fails
# the run's recording with one line instead of holding the run's end for ever
CLOSE_TIMEOUT_S = 120.0


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
    """Streams `rec` into a new file `path` (never an existing one); `pump()` once a step, `close()` at the end.
    next_free: when `path` exists, the first free of path-2, path-3... instead of an error (the file is created
    exclusively, so two runs started in the same second cannot both take a name)."""

    def __init__(self, rec: Any, path: str | Path, default_blueprint: Any = None, next_free: bool = False):
        self.path = Path(path)
        self.rec = rec
        first, n = self.path, 2
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            while True:
                try:
                    # unbuffered: a failed write raises in write(); closed by close() or on a failed write
                    self._file = open(self.path, "xb", buffering=0)  # noqa: SIM115
                    break
                except FileExistsError:
                    if not next_free:
                        raise
                    self.path = first.with_name(f"{first.stem}-{n}{first.suffix}")
                    n += 1
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot write the recording ({exc.strerror or exc})") from None
        self._stream = rec.binary_stream()
        if default_blueprint is not None:
            rec.send_blueprint(default_blueprint, make_active=False, make_default=True)
        self.written = 0  # bytes on disk, all of them complete messages
        self.failed: str | None = None
        self._error: RecordingError | None = None
        self._reported = False
        # The writes happen in this thread (as Rerun's own sink writes from its own): measured 5.6 ms a step on
        # average (up to 43 ms every 2 s, the batcher's tick) when done in the tracking thread.
        self._stop = threading.Event()
        self._writer = threading.Thread(target=self._write_loop, name="plvo-rrd-writer", daemon=True)
        self._writer.start()

    def _write_loop(self) -> None:
        while not self._stop.wait(WRITE_INTERVAL_S):
            try:
                self._write_pending()
            except RecordingError as exc:
                self._error = exc
                return
            except Exception as exc:  # noqa: BLE001 - e.g. the stream's encoder: the run must hear of it
                log.debug("the recording's writer thread failed", exc_info=True)
                self._error = RecordingError(f"{self.path}: writing the recording failed ({type(exc).__name__}: "
                                             f"{exc}); the {self.written} bytes written before are kept, readable")
                return

    def pump(self) -> None:
        """Once a step, in the caller's thread: raise the writer's first failure (once), so the run stops there."""
        if self._error is None and not self._writer.is_alive() and not self._stop.is_set():
            self._error = RecordingError(f"{self.path}: the recording's writer thread ended; the {self.written} "
                                         "bytes written before are kept, readable")
        if self._error is not None and not self._reported:
            self._reported = True
            raise self._error

    def _write_pending(self) -> None:
        """Write what the stream has encoded so far."""
        if self.failed is not None or self._file.closed:
            return
        data = self._stream.read(flush=False)
        if not data:
            return
        spans = message_spans(data)
        if not spans:
            return
        first = spans[0][0] if self.written else 0  # the stream header once, at the file's start
        ends = ([STREAM_HEADER] if not self.written else []) + [stop - first for _, stop in spans]
        self._write(memoryview(data)[first:spans[-1][1]], ends)

    def _write(self, chunk: memoryview, ends: list[int]) -> None:
        """Write `chunk` (whole messages ending at the offsets `ends`). On a failed write the file keeps every
        message that was written whole."""
        done = 0
        try:
            while done < len(chunk):
                done += self._file.write(chunk[done:])
        except OSError as exc:
            self.written += max((e for e in ends if e <= done), default=0)
            self._fail(exc)
        self.written += len(chunk)

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
        """Write the rest and close the file. A failure not yet raised by `pump` is raised here, once."""
        self._stop.set()
        self._writer.join(timeout=CLOSE_TIMEOUT_S)
        if self._error is not None and not self._writer.is_alive():  # the writer failed: nothing more is written
            self._close_file()
            if not self._reported:
                self.pump()
            return
        if self._writer.is_alive():  # its write is blocked: the file cannot be finished from here
            self._error = self._error or RecordingError(
                f"{self.path}: a write of the recording did not return within {CLOSE_TIMEOUT_S:.0f} s; the "
                f"{self.written} bytes written before are kept, readable")
            self._reported = False
            self.pump()
        if self._file.closed:
            self.pump()
            return
        try:
            self.rec.disconnect()  # ends the stream: everything logged is encoded
            self._write_pending()
        finally:
            self._close_file()
        if self.written == 0:
            os.unlink(self.path)  # an empty file would look like a recording
