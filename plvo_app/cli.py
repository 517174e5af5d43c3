"""Command-line entry points: `plvo-viz` and `plvo <subcommand>`.

Each subcommand lives in its own module `plvo_app.cmd_<name>` exposing `add_arguments(parser)` and `run(args)`;
only the chosen one is imported (`plvo --help` lists them from SUBCOMMANDS, importing none), and the command
modules import the pipeline, the datasets and the viewers inside the functions that use them, so that every
`--help` answers at once. -v shows INFO on the terminal, -vv DEBUG, -q errors only and no progress bar; the
default is warnings and errors (plvo_app.terminal).

A PlvoError is printed as one line and the process exits with its status (2: refused before the run, 1: failed
during it); Ctrl-C exits with 130, SIGTERM with 143; any other exception is one line naming a log with the traceback,
exit 1 (docs/faults.md).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import os
import sys
import tempfile
import traceback
import warnings
from collections.abc import Sequence
from types import ModuleType

# One OpenBLAS thread unless the user chose otherwise: set before anything imports numpy (the commands do), as
# OpenBLAS reads it once, when it loads. OpenBLAS's extra thread spins on 2 cores that the tracker, the line thread
# and the back end already share: on KITTI 04 (51 frames) the whole system used ~2.5x the CPU time with the default
# threads and ran 1.5-3.5x slower; set after the import, the tracking process kept two threads (the workers, which
# start later, one), whose second one spent 9 s spinning in a 271-frame twin run once the tracking thread deskewed.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from plvo.allocator import keep_freed_memory  # noqa: E402
from plvo.errors import PlvoError  # noqa: E402
from plvo_app.guards import (  # noqa: E402
    Terminated,
    exit_status_of,
    limit_reached,
    outlive_readers,
    sigterm_as_interrupt,
)
from plvo_app.terminal import QUIET, setup_terminal  # noqa: E402

# The tracking process reads, decodes and ships a frame's arrays every frame: keep freed memory for the next one
# (plvo.allocator; the worker processes do the same).
keep_freed_memory()

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("plvo_app.cmd_viz", "run the pipeline on a sequence (same as plvo-viz)"),
    "view": ("plvo_app.cmd_view", "inspect a saved .rrd recording in the viser viewer"),
    "synth": ("plvo_app.cmd_synth", "generate a synthetic town sequence in the KITTI odometry layout"),
    "eval": ("plvo_app.cmd_eval", "evaluate trajectories with the KITTI metric; run evaluations and ablations"),
    "reproduce": ("plvo_app.cmd_reproduce", "rerun a recording's frames with its config; report where it departs"),
    "clip": ("plvo_app.cmd_clip", "cut a recording down to a window of frames (for a bug report)"),
    "bench": ("plvo_app.cmd_bench", "time the stages and the whole system; writes JSON"),
    "vocab": ("plvo_app.cmd_vocab", "train the ORB and LBD bag-of-words vocabularies"),
    "calib": ("plvo_app.cmd_calib", "write a folder's calib.yaml from KITTI's; check a calibration on a frame"),
}


def _setup_logging(verbosity: int | bool) -> None:
    """The terminal's logging at `verbosity` (-1 quiet, 0 default, 1 -v, 2 -vv: plvo_app.terminal); a Python
    warning as one log line."""
    outlive_readers()  # first: the log handler and the progress bars take sys.stderr as they are made
    setup_terminal(int(verbosity))
    warnings.showwarning = _warning_line


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A Python warning as one log line (the default prints the warning's source line after it), e.g. the
    resource tracker's when it had to be started again after it died."""
    text = str(message).splitlines()[0] if str(message) else ""
    logging.getLogger("py.warnings").warning("%s: %s", category.__name__, text)


def _guarded(func, args) -> int:
    """Run a subcommand: a PlvoError is one line and its exit status; Ctrl-C 130, SIGTERM 143 (SIGHUP 129, SIGQUIT
    131: plvo_app.guards); any other exception (a bug) one line too, its traceback in a log file named on that line,
    exit 1."""
    with sigterm_as_interrupt():
        try:
            return int(func(args) or 0)
        except PlvoError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return exc.exit_status
        except KeyboardInterrupt as exc:
            print(f"terminated ({exc.name})" if isinstance(exc, Terminated) else "interrupted", file=sys.stderr)
            return exit_status_of(exc)
        except Exception as exc:  # noqa: BLE001 - the last resort
            where = _write_traceback()
            limit = limit_reached(exc)
            what = limit if limit is not None else f"unexpected {type(exc).__name__}: {exc}"
            print(f"error: {what} (see the log {where})", file=sys.stderr)
            return 1


def _write_traceback() -> str:
    try:
        fd, path = tempfile.mkstemp(prefix="plvo-traceback-", suffix=".log")
        with os.fdopen(fd, "w") as f:
            f.write(traceback.format_exc())
        return path
    except OSError:
        return "(it could not be written)"


def _add_verbosity(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-v", "--verbose", action="count", default=0,
                       help="show INFO log lines on the terminal (-vv: DEBUG, in run.log too); by default only "
                            "warnings and errors are shown, every INFO line is in the run's run.log")
    group.add_argument("-q", "--quiet", action="store_true",
                       help="show only errors and the results, no progress bar")


def _verbosity(args: argparse.Namespace) -> int:
    return QUIET if args.quiet else args.verbose


def _chosen(argv: Sequence[str]) -> str | None:
    """The subcommand named in argv: its first word that is not an option (plvo's own options take no value)."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return word
    return None


def _available() -> dict[str, tuple[str, str]]:
    """SUBCOMMANDS whose module exists (found, not imported: a subcommand not built yet is left out)."""
    out = {}
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        try:
            found = importlib.util.find_spec(module_name) is not None
        except ModuleNotFoundError:
            found = False
        if found:
            out[name] = (module_name, help_text)
    return out


def _parser(chosen: str | None) -> tuple[argparse.ArgumentParser, ModuleType | None]:
    """plvo's parser, every subcommand listed and only the chosen one's module imported, to make its arguments
    -> (parser, that module or None)."""
    parser = argparse.ArgumentParser(prog="plvo", description=__doc__.splitlines()[0])
    _add_verbosity(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    module = None
    for name, (module_name, help_text) in _available().items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
    return parser, module


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = _chosen(argv)
    parser, module = _parser(chosen)
    args = parser.parse_args(argv)  # --help, an unknown command: argparse's answer and exit, before any import
    if args.command != chosen:  # named where _chosen did not look (after "--"): parse again with its arguments
        parser, module = _parser(args.command)
        args = parser.parse_args(argv)
    assert module is not None
    _setup_logging(_verbosity(args))
    _quiet_progress(args)
    return _guarded(module.run, args)


def _quiet_progress(args: argparse.Namespace) -> None:
    """-q: the commands with a --no-progress option (synth, vocab) draw no bar either."""
    if args.quiet and hasattr(args, "no_progress"):
        args.no_progress = True


def main_viz(argv: Sequence[str] | None = None) -> int:
    from plvo_app import cmd_viz

    parser = argparse.ArgumentParser(prog="plvo-viz", description=cmd_viz.__doc__.splitlines()[0])
    _add_verbosity(parser)
    cmd_viz.add_arguments(parser)
    args = parser.parse_args(argv)
    _setup_logging(_verbosity(args))
    return _guarded(cmd_viz.run, args)


if __name__ == "__main__":
    sys.exit(main())
