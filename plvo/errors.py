"""Errors raised on bad input or a failed output. Every message names the file, frame or field at fault.

The CLI prints any PlvoError as one line `error: <message>` and exits with its `exit_status`: 2 for what was refused
before a run started (bad input, arguments, outputs), 1 for a run that failed while going (docs/faults.md).
"""

from __future__ import annotations


class PlvoError(Exception):
    """Base class: the CLI prints the message on one line and exits non-zero."""

    exit_status = 2


class DatasetError(PlvoError):
    """A dataset file is missing, unreadable or inconsistent (names the file and frame)."""


class CalibrationError(DatasetError):
    """A calibration file lacks a matrix or has one of the wrong shape (names the file and key)."""


class TrajectoryError(PlvoError):
    """A pose file is missing or malformed (names the file and line)."""


class ConfigError(PlvoError):
    """A config file has an unknown key or a value of the wrong type (names the key)."""


class SynthError(PlvoError):
    """Impossible settings for the synthetic town generator (names the setting)."""


class RecordingError(PlvoError):
    """A recording cannot be written or read back (names the file)."""


class ArgumentsError(PlvoError):
    """A command-line argument is out of range or names something unusable (names the option)."""


class OutputError(PlvoError):
    """An output folder or file cannot be written, or there is no room for it (names the path)."""


class RunFailed(PlvoError):
    """A run stopped part-way: a write failed, it tracked too little, or an unexpected error (names the frame)."""

    exit_status = 1


class WorkerError(PlvoError):
    """A back-end or loop-closer worker failed (names the worker, keyframe and frame)."""

    exit_status = 1
