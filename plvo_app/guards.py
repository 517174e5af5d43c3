"""Signals and ports, checked the same way by every command.

SIGTERM (what `timeout`, `docker stop` and service managers send) is turned into `Terminated`, a KeyboardInterrupt,
so that it takes Ctrl-C's path: the recording is stamped and closed, the results written and marked. During that
clean-up `deferred_signals` holds further Ctrl-C / SIGTERM back (a second Ctrl-C must not lose the results).
"""

from __future__ import annotations

import errno
import logging
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


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C, exits with 143."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within: SIGTERM raises Terminated in the main thread (elsewhere signals cannot be set: left alone)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


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
    """Within: Ctrl-C and SIGTERM are noted (once on stderr) but do not interrupt `what`."""
    held = Held(what)
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    previous = {s: signal.signal(s, held.note) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield held
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def exit_status_of(interrupt: KeyboardInterrupt) -> int:
    return EXIT_TERMINATED if isinstance(interrupt, Terminated) else EXIT_INTERRUPTED


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
