"""Errors raised on bad input. Every message names the file, frame or field at fault."""

from __future__ import annotations


class PlvoError(Exception):
    """Base class: the CLI prints the message on one line and exits non-zero."""


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


class WorkerError(PlvoError):
    """A back-end or loop-closer worker failed (names the worker, keyframe and frame)."""
