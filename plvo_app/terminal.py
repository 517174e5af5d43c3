"""What the terminal shows of a command, and at which -v/-q.

  verbosity  terminal (stderr)                   run.log (plvo-viz's results folder)  progress bars
  -q (-1)    errors                              INFO and up                          none
  (0)        warnings and errors                 INFO and up                          shown
  -v (1)     INFO and up                         INFO and up                          shown
  -vv (2)    DEBUG and up                        DEBUG and up                         shown

plvo's own lines (where the results are, the final summary, one-line errors) are printed whatever the verbosity:
they are the result. A log record is written above the progress bars (tqdm.write) while any bar is shown, so that
no line is glued to a bar. `setup_terminal` (plvo_app.cli) sets the verbosity; `progress_enabled` says whether a
command draws its bars; `file_level` is the level of the run's log. The root logger's level is the lowest that
anything wants (the terminal or run.log), which is also the level the worker processes ship records back at
(plvo.runtime.workers): DEBUG records are made, in the workers too, only under -vv.
"""

from __future__ import annotations

import logging
import sys

QUIET, NORMAL, VERBOSE, DEBUG = -1, 0, 1, 2
FORMAT = "%(levelname)s %(name)s: %(message)s"

_verbosity = NORMAL


def verbosity() -> int:
    return _verbosity


def terminal_level(v: int | None = None) -> int:
    """The lowest level the terminal shows at verbosity v (default: the current one)."""
    v = _verbosity if v is None else v
    return {QUIET: logging.ERROR, NORMAL: logging.WARNING, VERBOSE: logging.INFO}.get(
        max(QUIET, min(DEBUG, v)), logging.DEBUG)


def file_level(v: int | None = None) -> int:
    """The lowest level a run's log file (run.log) keeps at verbosity v (default: the current one)."""
    v = _verbosity if v is None else v
    return logging.DEBUG if v >= DEBUG else logging.INFO


def progress_enabled() -> bool:
    """Whether commands draw progress bars (not under -q)."""
    return _verbosity > QUIET


class TerminalHandler(logging.Handler):
    """Log records on the current sys.stderr (looked up at each record: plvo_app.guards wraps it, a test captures
    it), written above the progress bars while any tqdm bar is shown."""

    def __init__(self, level: int = logging.NOTSET):
        super().__init__(level)
        self.setFormatter(logging.Formatter(FORMAT))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = self.format(record)
            stream = sys.stderr
            if stream is None:
                return
            bars = _tqdm_class()
            if bars is not None and getattr(bars, "_instances", None):
                bars.write(msg, file=stream)  # clears the bars, writes the line, draws the bars again
            else:
                stream.write(msg + "\n")
                stream.flush()
        except RecursionError:
            raise
        except Exception:  # noqa: BLE001 - logging's own rule: a failing handler reports, never raises
            self.handleError(record)


def _tqdm_class():
    """tqdm's bar class if tqdm is imported (a bar can only be shown then; it is not imported for it here)."""
    std = sys.modules.get("tqdm.std")
    return getattr(std, "tqdm", None) if std is not None else None


def setup_terminal(v: int) -> None:
    """Set the verbosity: the terminal's log handler at its level, the root logger at the lowest level wanted.

    As logging.basicConfig does, a root logger that already has handlers other than this module's (a program
    that embeds plvo's commands, pytest) is left as it is; only the verbosity (progress bars, run.log's level) is
    set then."""
    global _verbosity
    _verbosity = max(QUIET, min(DEBUG, int(v)))
    root = logging.getLogger()
    ours = [h for h in root.handlers if isinstance(h, TerminalHandler)]
    if len(ours) != len(root.handlers):
        return
    for h in ours:
        root.removeHandler(h)
    root.addHandler(TerminalHandler(terminal_level()))
    root.setLevel(min(terminal_level(), file_level()))
