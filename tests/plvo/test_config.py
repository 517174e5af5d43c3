"""Config: the paper's defaults, TOML round trip, unknown keys rejected by name, ablations."""

from __future__ import annotations

import pytest

from plvo.config import (
    ABLATIONS,
    SystemConfig,
    config_to_toml,
    load_config,
    save_config,
    with_ablation,
)
from plvo.errors import ConfigError


def test_paper_defaults():
    cfg = SystemConfig()
    assert cfg.orb.n_features == 1000
    assert cfg.lines.min_length_px == 50.0
    assert cfg.matching.line_angle_deg == 2.0
    assert cfg.matching.line_length_ratio == 0.1
    assert cfg.matching.line_midpoint_px == 5.0
    assert cfg.backend.sigma_point_px == 0.1
    assert cfg.backend.sigma_line == 0.2
    assert 3 <= cfg.tracking.keyframe_every <= cfg.tracking.keyframe_max_gap <= 4


def test_toml_round_trip(tmp_path):
    cfg = with_ablation(SystemConfig(), "points_only")
    path = tmp_path / "config.toml"
    save_config(cfg, path)
    assert load_config(path) == cfg
    assert not list(tmp_path.glob(".*part"))  # the atomic write left no temporary file


def test_partial_file_keeps_other_defaults(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[orb]\nn_features = 500\n[backend]\nsigma_line = 1\n")
    cfg = load_config(path)
    assert cfg.orb.n_features == 500
    assert cfg.backend.sigma_line == 1.0 and isinstance(cfg.backend.sigma_line, float)
    assert cfg.lines == SystemConfig().lines


@pytest.mark.parametrize(
    "text, key",
    [
        ("[orb]\nn_featurs = 5\n", "orb.n_featurs"),
        ("[nosuch]\nx = 1\n", "nosuch"),
        ("orb = 3\n", "orb"),
        ("[orb]\nn_features = 'many'\n", "orb.n_features"),
        ("[tracking]\npoints_only = 1\n", "tracking.points_only"),
        ("[tracking]\nrescue_yaw_deg = ['a']\n", "tracking.rescue_yaw_deg"),
        ("[tracking]\nrescue_yaw_deg = 6\n", "tracking.rescue_yaw_deg"),
    ],
)
def test_bad_keys_are_named(tmp_path, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert key in str(err.value) and str(path) in str(err.value)


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.toml")
    (tmp_path / "x.toml").write_text("[orb\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(tmp_path / "x.toml")


def test_ablations_change_what_they_say():
    base = SystemConfig()
    assert set(ABLATIONS) == {"full", "no_depth_priors", "no_scale_correction", "points_only", "tracker_only",
                              "no_scale_step", "no_deskew", "keyframe_ndt", "no_lidar_loops"}
    assert with_ablation(base, "full") == base
    assert with_ablation(base, "no_depth_priors").tracking.use_depth_priors is False
    module_off = with_ablation(base, "no_scale_correction").backend
    assert module_off.scale_correction is False and module_off.registration is False and module_off.enabled
    step_off = with_ablation(base, "no_scale_step").backend
    assert step_off.scale_correction is False and step_off.registration is True
    assert with_ablation(base, "points_only").tracking.points_only is True
    alone = with_ablation(base, "tracker_only")
    assert alone.backend.enabled is False and alone.loop.enabled is False and alone.tracking == base.tracking
    assert with_ablation(base, "no_deskew").registration.deskew == "off" != base.registration.deskew
    assert with_ablation(base, "keyframe_ndt").backend.lidar_target == "keyframe" != base.backend.lidar_target
    assert with_ablation(base, "no_lidar_loops").loop.lidar_place is False and base.loop.lidar_place is True
    with pytest.raises(ConfigError, match="unknown ablation"):
        with_ablation(base, "nope")


def test_toml_text_is_readable():
    text = config_to_toml(SystemConfig())
    assert "[orb]" in text and "n_features = 1000" in text


def test_every_numeric_field_declares_its_range_and_unit_beside_it():
    """The contract of a field is where the field is: its range and unit in its declaration (plvo.config_fields
    .setting), a unit its name states (`_m`, `_px`, `_deg`, `_s`) the one declared, and a field declared without
    a range refused when the config is checked."""
    import dataclasses

    from plvo.config_fields import SUFFIX_UNITS, Range, check_ranges, numeric_fields, setting

    fields = numeric_fields(SystemConfig())
    assert len(fields) > 150
    for key, decl in fields.items():
        assert isinstance(decl.valid, Range), key
        named = next((u for suffix, u in SUFFIX_UNITS.items() if key.endswith(suffix)), None)
        assert named is None or decl.unit == named, (key, decl.unit)
    assert fields["registration.voxel_m"].unit == "m" and fields["loop.odom_sigma_rot"].unit == "rad"
    assert fields["orb.n_features"].unit == "features" and fields["lines.lsd_scale"].unit == ""

    @dataclasses.dataclass(frozen=True)
    class Part:
        declared: float = setting(1.0, Range(0.0, 2.0), "m")
        undeclared_m: float = 1.0

    @dataclasses.dataclass(frozen=True)
    class Whole:
        part: Part = dataclasses.field(default_factory=Part)

    with pytest.raises(ConfigError, match="'part.undeclared_m' has no declared range"):
        check_ranges(Whole())
    assert numeric_fields(Whole())["part.declared"].valid == Range(0.0, 2.0)


def test_each_part_is_built_from_its_own_sections():
    """The tracker, the back end and the loop closer are given the sections they read, the very objects of the
    config, and nothing else (a part reading another section fails at once, not with a silently default value)."""
    from plvo.config import BackendSections, LoopSections, TrackerSections

    cfg = with_ablation(SystemConfig(), "points_only")
    tracker = cfg.sections(TrackerSections)
    assert tracker.tracking is cfg.tracking and tracker.tracking.points_only
    assert set(TrackerSections._fields) == {"orb", "lines", "matching", "depth", "tracking", "crosscheck",
                                            "registration"}
    assert not hasattr(tracker, "backend") and not hasattr(tracker, "loop")
    assert cfg.sections(BackendSections).backend is cfg.backend and not hasattr(cfg.sections(BackendSections), "orb")
    assert cfg.sections(LoopSections).loop is cfg.loop and not hasattr(cfg.sections(LoopSections), "depth")
