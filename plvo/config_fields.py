"""How a config field is declared and checked: each numeric field of `plvo.config` carries its valid range and its
unit beside it (`setting(default, range, unit)`), each choice field its values as its type (a Literal).

Checked when a config is read (plvo.config.config_from_dict): zero or negative counts, sizes and factors would be
accepted silently or crash deep inside OpenCV or GTSAM, so a value out of its range is refused with the dotted key,
the value and the range. A numeric field without a declared range is refused too (tests/plvo/test_config.py
checks every one), so a new field comes with its range and unit.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from plvo.errors import ConfigError


@dataclass(frozen=True)
class Range:
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def __str__(self) -> str:
        if self.hi == math.inf:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


POSITIVE = Range(0.0, lo_open=True)  # sizes, distances, factors, sigmas: zero is meaningless
NON_NEGATIVE = Range(0.0)  # thresholds where 0 means "off"
COUNT = Range(1)  # counts and iterations: at least one
COUNT0 = Range(0)  # counts where 0 means "none"
SHARE = Range(0.0, 1.0)  # fractions
RATIO = Range(0.0, 1.0, lo_open=True)  # Lowe ratios and scales: (0, 1]
ANGLE = Range(0.0, 90.0, lo_open=True)  # angular tolerances between lines, degrees
HAMMING = Range(0, 256)  # 256-bit ORB / LBD descriptors
COSINE = Range(0.0, 1.0, hi_open=True)

T = TypeVar("T")


def setting(default: T, valid: Range, unit: str = "") -> T:
    """A numeric config field: its default, the range a value must lie in and its unit ("m", "px", "deg", "s",
    "rad", what a count counts; "" for ratios and shares), kept in the field's metadata where the check reads them."""
    return field(default=default, metadata={"valid": valid, "unit": unit})


@dataclass(frozen=True)
class Declared:
    """A numeric field as declared: its value in a config, its range, its unit."""

    value: Any
    valid: Range | None
    unit: str

    @property
    def is_int(self) -> bool:
        return all(isinstance(v, int) for v in self.items)

    @property
    def items(self) -> tuple[Any, ...]:
        return self.value if isinstance(self.value, tuple) else (self.value,)


# Pairs that must be ordered: (smaller key, larger key).
ORDERED: tuple[tuple[str, str], ...] = (
    ("orb.fast_threshold_min", "orb.fast_threshold"),
    ("tracking.keyframe_every", "tracking.keyframe_max_gap"),
    ("registration.min_range_m", "registration.max_range_m"),
    ("crosscheck.min_range_m", "crosscheck.max_range_m"),
    ("depth.min_depth_m", "depth.max_depth_m"),
    ("depth.adapt_min_ratio", "depth.adapt_max_ratio"),
)


def choices_of(hint: Any) -> tuple[str, ...]:
    """The values a choice field takes (its type a Literal, or a union of Literals: the choices stand beside the
    field in plvo.config); () for any other type."""
    if typing.get_origin(hint) is typing.Literal:
        return tuple(typing.get_args(hint))
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        parts = [choices_of(a) for a in typing.get_args(hint)]
        return tuple(v for p in parts for v in p) if all(parts) else ()
    return ()


def choice_fields(cfg: Any) -> dict[str, tuple[tuple[str, ...], Any]]:
    """Dotted key -> (its choices, its value) of every choice field of a (nested) config dataclass. Checked when
    a file is read, also those used only off the defaults' path (a typo there would otherwise pass until a run
    took that path)."""
    out: dict[str, tuple[tuple[str, ...], Any]] = {}
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            if choices_of(hints[f.name]):
                out[f"{section.name}.{f.name}"] = (choices_of(hints[f.name]), getattr(sub, f.name))
    return out


# Every numeric field is bounded above too: by its range, else by the cap of its unit, else by the cap of its kind.
# A count of 1e12 features, a window of a million keyframes or a timeout of 1e30 s would pass a lower bound alone
# and exhaust the memory or wait for ever.
UNIT_CAPS: dict[str, float] = {"m": 1e5, "px": 1e5, "deg": 360.0, "rad": 6.3, "s": 3600.0}
# A field named by its unit (`voxel_m`, `agree_deg`) declares that unit
SUFFIX_UNITS: dict[str, str] = {"_m": "m", "_px": "px", "_deg": "deg", "_s": "s"}
COUNT_CAP = 1e8  # int fields: counts, iterations, gaps
FACTOR_CAP = 1e6  # other float fields: factors, sigmas, weights, powers


def bounded(rng: Range, unit: str, is_int: bool) -> Range:
    """`rng` with its upper bound capped (UNIT_CAPS by the unit, else COUNT_CAP / FACTOR_CAP)."""
    cap = UNIT_CAPS.get(unit, COUNT_CAP if is_int else FACTOR_CAP)
    return rng if rng.hi <= cap else dataclasses.replace(rng, hi=cap, hi_open=False)


def numeric_fields(cfg: Any) -> dict[str, Declared]:
    """Dotted key -> the declaration of every int, float or tuple-of-numbers field of a (nested) config dataclass."""
    out: dict[str, Declared] = {}
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            want = hints[f.name]
            if want in (int, float) or typing.get_origin(want) is tuple:
                out[f"{section.name}.{f.name}"] = Declared(getattr(sub, f.name), f.metadata.get("valid"),
                                                           f.metadata.get("unit", ""))
    return out


def check_ranges(cfg: Any) -> None:
    """Raise ConfigError naming the first dotted key whose value is out of its range (or has no range)."""
    fields = numeric_fields(cfg)
    for key, decl in fields.items():
        if decl.valid is None:
            raise ConfigError(f"config key '{key}' has no declared range (plvo.config: setting(default, range, unit))")
        rng = bounded(decl.valid, decl.unit, decl.is_int)
        for v in decl.items:
            if not rng.contains(float(v)):
                raise ConfigError(f"config key '{key}' = {v!r} is out of range (must be {rng})")
    for key, (allowed, value) in choice_fields(cfg).items():
        if value not in allowed:
            raise ConfigError(f"config key '{key}' = {value!r} must be one of {', '.join(allowed)}")
    vocab = getattr(getattr(cfg, "loop", None), "vocab_dir", "")
    if vocab:  # read by the loop closer's process at its start: a wrong folder said here, not as a worker's failure
        missing = [n for n in ("orb.npz", "lbd.npz") if not (Path(vocab) / n).is_file()]
        if missing:
            raise ConfigError(f"config key 'loop.vocab_dir' = {vocab!r}: no {' or '.join(missing)} there "
                              "(plvo vocab --out writes them; empty: the shipped vocabularies)")
    correction = getattr(getattr(cfg, "crosscheck", None), "extrinsic_correction_deg", (0.0, 0.0, 0.0))
    if len(correction) != 3:
        raise ConfigError(f"config key 'crosscheck.extrinsic_correction_deg' = {list(correction)!r} must be three "
                          "angles (a rotation vector, degrees)")
    for small, large in ORDERED:
        if fields[small].value > fields[large].value:
            raise ConfigError(f"config key '{small}' = {fields[small].value!r} must not exceed '{large}' = "
                              f"{fields[large].value!r}")
