"""Signals and ports, checked the same way by every command.

SIGTERM (what `timeout`, `docker stop` and service managers send), SIGHUP (a closed terminal, a dropped ssh
connection), SIGQUIT (Ctrl-\\) and SIGUSR1/2 end a process by default, with no word and nothing written. Each is
turned into `Terminated`, a KeyboardInterrupt, so that it takes Ctrl-C's path: the recording is stamped and closed,
the results written and marked, exit 128 + the signal's number. During that clean-up `deferred_signals` holds further
signals back (a second Ctrl-C must not lose the results).
"""

from __future__ import annotations

import errno
import io
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from plvo.errors import ArgumentsError

log = logging.getLogger(__name__)

EXIT_INTERRUPTED = 128 + signal.SIGINT  # 130, as a shell reports Ctrl-C
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143
# The signals whose default action ends the process without a word (SIGKILL and SIGSTOP cannot be caught)
ENDING_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2)


class Terminated(KeyboardInterrupt):
    """A signal that ends a process arrived (SIGTERM by default): handled like Ctrl-C, exits with 128 + its number."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def _raise_terminated(signum, frame) -> None:
    raise Terminated(signum)


def signal_name(interrupt: KeyboardInterrupt) -> str:
    """'SIGTERM', 'SIGHUP', ... for a Terminated; 'Ctrl-C' for a KeyboardInterrupt of SIGINT."""
    return interrupt.name if isinstance(interrupt, Terminated) else "Ctrl-C"


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within: SIGTERM and the other ENDING_SIGNALS raise Terminated in the main thread (elsewhere signals cannot be
    set: left alone)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise_terminated) for s in ENDING_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class Held:
    """The signals `deferred_signals` held back (`seen`); `what` is said on the first one (None: say nothing)."""

    def __init__(self, what: str | None):
        self.what = what
        self.seen: list[int] = []

    def note(self, signum, frame) -> None:
        if not self.seen and self.what:
            print(f"{signal.Signals(signum).name}: finishing {self.what} first", file=sys.stderr)
        self.seen.append(signum)


@contextmanager
def deferred_signals(what: str) -> Iterator[Held]:
    """Within: Ctrl-C, SIGTERM and the other ENDING_SIGNALS are noted (once on stderr) but do not interrupt `what`."""
    held = Held(what)
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    previous = {s: signal.signal(s, held.note) for s in (signal.SIGINT, *ENDING_SIGNALS)}
    try:
        yield held
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class ReaderlessStream:
    """sys.stderr or sys.stdout made to outlive its reader: once a write or flush fails because nobody reads any
    more (`plvo-viz ... 2>&1 | head` has exited: EPIPE; the terminal was closed: EIO), later output is dropped
    instead of failing the run as an unexpected error; the run goes on and writes its results. Everything else is
    the wrapped stream's."""

    _GONE = (errno.EPIPE, errno.EIO, errno.ECONNRESET)

    def __init__(self, stream):
        self._stream = stream
        self.gone = False

    def _lost(self, exc: OSError) -> None:
        if exc.errno not in self._GONE and not isinstance(exc, BrokenPipeError):
            raise exc
        self.gone = True
        # what the stream still buffers is flushed at the exit: into /dev/null, not into a failure (exit 120)
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)
        except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
            pass

    def write(self, text: str) -> int:
        if not self.gone:
            try:
                return self._stream.write(text)
            except OSError as exc:
                self._lost(exc)
        return len(text)

    def flush(self) -> None:
        if not self.gone:
            try:
                self._stream.flush()
            except OSError as exc:
                self._lost(exc)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def outlive_readers() -> None:
    """Wrap sys.stdout and sys.stderr in ReaderlessStream (once): call before any handler or bar takes them."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, ReaderlessStream):
            setattr(sys, name, ReaderlessStream(stream))


def limit_reached(exc: BaseException) -> str | None:
    """What a resource limit looks like when it ends a command (too few open files, no thread or process can be
    started, no memory), in words that name the limit; None for any other exception (a bug: "unexpected")."""
    import resource

    if isinstance(exc, OSError) and exc.errno in (errno.EMFILE, errno.ENFILE):
        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        return (f"too many open files (this process may open {soft}; a plvo-viz run opens about 30 at once, more "
                "with the viewer: raise it with `ulimit -n`)")
    if isinstance(exc, RuntimeError) and "can't start new thread" in str(exc):
        return "a thread could not be started (a limit on memory or processes: `ulimit -v`, `ulimit -u`?)"
    if isinstance(exc, MemoryError) or (isinstance(exc, OSError) and exc.errno in (errno.ENOMEM, errno.EAGAIN)):
        return f"out of memory or processes ({type(exc).__name__}: {exc}; a limit: `ulimit -v`, `ulimit -u`?)"
    if isinstance(exc, ImportError) and "failed to map segment" in str(exc):
        return f"a library could not be loaded: out of memory ({exc}; a limit: `ulimit -v`?)"
    return None


def exit_status_of(interrupt: KeyboardInterrupt) -> int:
    return 128 + interrupt.signum if isinstance(interrupt, Terminated) else EXIT_INTERRUPTED


def check_port(port: int, option: str = "--port", host: str = "127.0.0.1") -> int:
    """`port` if it is in 1-65535 and free on `host`; else ArgumentsError naming the option (a busy port is
    refused rather than replaced by another without a word)."""
    if not 1 <= int(port) <= 65535:
        raise ArgumentsError(f"{option} {port}: a port must be in 1-65535")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers bind: TIME_WAIT is not "busy"
        try:
            s.bind((host, int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ArgumentsError(f"{option} {port}: port {port} on {host} is in use; choose another") from None
            raise ArgumentsError(f"{option} {port}: cannot listen on {host}:{port} ({exc.strerror})") from None
    return int(port)
