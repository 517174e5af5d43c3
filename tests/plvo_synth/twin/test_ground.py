"""The realistic twins' ground (plvo_synth.twin.ground): dashed lane lines of the set dash and gap, paving
stones of the set size, asphalt whose texture no longer repeats with the atlas's tile, an uneven shade of the set
spread, markings the same whichever way the road is driven, and the ideal ground shaded as before. A straight
160 m road rendered from 25 m straight above (the ground then lies at one depth: metres per pixel are constant);
no twin is written."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plvo.errors import SynthError
from plvo_synth.kitti_calib import CALIB_00_02
from plvo_synth.textures import MATERIAL_ID, build_atlas
from plvo_synth.twin.camera_effects import IDEAL_CAMERA
from plvo_synth.twin.ground import (
    EDGE_LINE,
    IDEAL_GROUND,
    REALISTIC_GROUND,
    GroundRealism,
    GroundShader,
    pulse_train,
)
from plvo_synth.twin.layout import ZONES, Layout
from plvo_synth.twin.lidars import lidar_model
from plvo_synth.twin.render import TwinRenderer
from plvo_synth.twin.scenery import build_world
from plvo_synth.twin.scenery_realism import IDEAL_SCENERY, REALISTIC_SCENERY
from plvo_synth.twin.traffic import Traffic

M = MATERIAL_ID
SEED = 2
SPEED = 6.0
HEIGHT_M = 25.0
ROAD_Y = 0.0
TILE_PERIOD_M = 256 / 64.0  # the atlas's asphalt tile: 256 texels at 64 texels a metre


def _straight(reverse: bool = False) -> np.ndarray:
    s = np.arange(0.0, 160.0, 1.0)
    road = np.column_stack([s, np.full(len(s), ROAD_Y), np.zeros(len(s))])
    return road[::-1] if reverse else road


def _layout(road: np.ndarray) -> Layout:
    return Layout(road, road, np.full(len(road), SPEED), SEED)


@pytest.fixture(scope="module")
def scene():
    layout = _layout(_straight())
    town, n_ground, _ = build_world(layout, SEED, IDEAL_SCENERY)
    traffic = Traffic(layout, _straight(), 0, 2, 0, SEED)
    return layout, town, n_ground, traffic, build_atlas(SEED)


def _top_down(scene, ground: GroundRealism, x_m: float = 80.0):
    """The road rendered from HEIGHT_M above (x_m, ROAD_Y), image rows across it, columns along it -> image,
    depth, metres a pixel, and the pixel of (x_m, ROAD_Y)."""
    layout, town, n_ground, traffic, atlas = scene
    r = TwinRenderer(town, n_ground, layout, traffic, lidar_model("hdl64"), atlas, SEED, CALIB_00_02, ground=ground)
    T = np.eye(4)
    # cam0's x along the road (+x), its y towards -y, its z straight down
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = [x_m, ROAD_Y, HEIGHT_M]
    image, depth, *_ = r.render_twin(T, 0.0, np.random.default_rng(0), IDEAL_CAMERA)
    K = CALIB_00_02.K
    return image.astype(np.float64), depth, HEIGHT_M / K[0, 0], (K[0, 2], K[1, 2])


def _runs(mask: np.ndarray) -> tuple[list[int], list[int]]:
    """Lengths of the complete runs of True and of False in a 1-D mask (the runs touching its ends left out)."""
    edges = np.flatnonzero(np.diff(mask.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [len(mask)]])
    on, off = [], []
    for a, b in zip(bounds[1:-2], bounds[2:-1]):
        (on if mask[a] else off).append(int(b - a))
    return on, off


def test_dashed_lane_lines_have_the_set_dash_and_gap(scene):
    """Along the lane line beside the driven path (lane_width_m / 2 to its left), the paint's runs measure the
    zone's dash and gap within two pixels (7 cm); elsewhere across the lane there is no paint."""
    dash, gap = 2.0, 4.0
    ground = dataclasses.replace(REALISTIC_GROUND, dash_m=(dash,) * 4, gap_m=(gap,) * 4, wear_contrast=0.0)
    image, depth, m_px, (cx, cy) = _top_down(scene, ground)
    row = int(round(cy - ground.lane_width_m / 2 / m_px))  # world +y is image up
    flat = np.abs(depth - HEIGHT_M) < 0.05
    assert flat[row - 2:row + 3].all(), "the lane line is hidden from above"
    profile = image[row - 1:row + 2].max(axis=0)
    lane = image[int(round(cy - 0.9 / m_px))]  # the middle of the ego lane: asphalt only
    threshold = 0.5 * (np.median(lane) + profile.max())
    on, off = _runs(profile > threshold)
    assert len(on) >= 4 and len(off) >= 4, (on, off)
    assert np.all(np.abs(np.array(on) * m_px - dash) < 2 * m_px + 1e-9), np.array(on) * m_px
    assert np.all(np.abs(np.array(off) * m_px - gap) < 2 * m_px + 1e-9), np.array(off) * m_px
    assert (lane > threshold).mean() < 0.001


def test_paving_stones_have_the_set_size():
    """On a city pavement the joints (the darkest texels) recur every stone length along the road and every stone
    width across it (shaded at 1 mm a sample, no footprint)."""
    layout = _layout(_straight())
    shader = GroundShader(dataclasses.replace(REALISTIC_GROUND, paver_m=(0.3, 0.15)), layout, build_atlas(SEED), SEED)
    for along, length in ((True, 0.3), (False, 0.15)):
        t = np.arange(0.0, 3.0, 0.001)
        s_along = 50.0 + (t if along else 0.0 * t)
        across = 9.03 + (0.0 * t if along else t)  # a row's middle, clear of the joints across
        shade = shader.pavers(s_along, across, 0.0, 0.0)
        joints = shade < 0.8
        starts = np.flatnonzero(np.diff(joints.astype(np.int8)) == 1)
        spacing = np.diff(starts) * 0.001
        assert len(spacing) >= 8 and np.allclose(spacing, length, atol=0.002), spacing


def test_asphalt_no_longer_repeats_with_the_tile(scene):
    """A rendered strip of asphalt along the ego lane: with the atlas's tile its brightness correlates with itself
    one tile period (4 m) along the road at over 0.8; the aperiodic ground's (no wear, no markings, the tile's
    full contrast) at under 0.3."""

    def period_correlation(ground: GroundRealism) -> float:
        image, depth, m_px, (cx, cy) = _top_down(scene, ground)
        rows = [int(round(cy - y / m_px)) for y in (-1.2, -0.6, 0.6, 1.2)]  # within the lane, off any line
        lag = int(round(TILE_PERIOD_M / m_px))
        corr = []
        for r in rows:
            assert (np.abs(depth[r] - HEIGHT_M) < 0.05).all()
            corr.append(float(np.corrcoef(image[r, :-lag], image[r, lag:])[0, 1]))
        return float(np.mean(corr))

    plain = dataclasses.replace(IDEAL_GROUND, paver_m=(0.2, 0.1))  # realistic code path, the tile as it is
    aperiodic = dataclasses.replace(plain, aperiodic=True)
    assert period_correlation(plain) > 0.8
    assert period_correlation(aperiodic) < 0.3


def test_wear_has_the_set_spread():
    """The asphalt's uneven shade over 200 x 200 m: its spread is wear_contrast within 20 %, and it repeats
    nowhere (its correlation one wear tile away is under 0.2)."""
    layout = _layout(_straight())
    for contrast in (0.1, 0.3):
        shader = GroundShader(dataclasses.replace(REALISTIC_GROUND, wear_contrast=contrast), layout,
                              build_atlas(SEED), SEED)
        g = np.arange(0.0, 200.0, 0.5)
        xy = np.column_stack([np.repeat(g, len(g)), np.tile(g, len(g))])
        w = shader._wear_at(xy)
        assert abs(np.std(w) / contrast - 1.0) < 0.2, np.std(w)
    period = 256 * REALISTIC_GROUND.wear_scale_m / 8.0
    a = shader._wear_at(xy) - 1.0
    b = shader._wear_at(xy + [period, 0.0]) - 1.0
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.2


def test_markings_do_not_depend_on_the_driving_direction():
    """A winding road and the same road driven the other way: every ground point is shaded alike (arc length and
    offset come from the place, not the order of the samples)."""
    s = np.arange(0.0, 160.0, 1.0)
    road = np.column_stack([s, 8.0 * np.sin(s / 40.0), 0.02 * s])
    atlas = build_atlas(SEED)
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(10.0, 150.0, 20000), rng.uniform(-15.0, 15.0, 20000)])
    out = []
    for layout in (_layout(road), _layout(road[::-1])):
        shader = GroundShader(REALISTIC_GROUND, layout, atlas, SEED)
        d, k = layout.nearest(xy)
        out.append(shader.albedo(xy, d, k, xy[:, 0], xy[:, 1], np.full(len(xy), 0.02), np.full(len(xy), 0.02)))
        painted = shader.markings(*layout.road_coords(xy, k), d - layout.half_width[k], layout.zone[k].astype(int),
                                  layout.on_path[k], layout.half_width[k], 0.02, 0.02)
        assert 0.005 < (painted > 0.5).mean() < 0.1  # lane lines and edge lines on the road
    assert np.allclose(out[0], out[1], atol=1e-5)


def test_pulse_train_is_the_dash_share_over_the_footprint():
    """Box-filtered dashes: a footprint of whole periods sees the dash's share of a period, a point sees 0 or 1."""
    x = np.linspace(0.0, 30.0, 301)
    assert np.allclose(pulse_train(x, 9.0, 3.0, 18.0), 3.0 / 9.0)
    assert set(np.unique(pulse_train(x, 9.0, 3.0, 0.0))) == {0.0, 1.0}


def test_ideal_ground_is_shaded_as_before(scene):
    """IDEAL_GROUND (the ideal scenery's) builds no shader and shades road, edge line, kerb and verge as the twins
    did before: the atlas's tiles by distance to the road (the rule restated here)."""
    assert IDEAL_SCENERY.ground == IDEAL_GROUND and IDEAL_GROUND.is_ideal
    assert REALISTIC_SCENERY.ground == REALISTIC_GROUND and not REALISTIC_GROUND.is_ideal
    layout, town, n_ground, traffic, atlas = scene
    r = TwinRenderer(town, n_ground, layout, traffic, lidar_model("hdl64"), atlas, SEED, CALIB_00_02)
    assert r._ground_shader is None
    rng = np.random.default_rng(5)
    xy = np.column_stack([rng.uniform(10.0, 150.0, 5000), rng.uniform(-20.0, 20.0, 5000)])
    fp = rng.uniform(0.005, 0.2, 5000).astype(np.float32)
    d, k = layout.nearest(xy)
    inside = d - layout.half_width[k]
    verge = np.where(layout.zone[k] == 0, M["pavement"], M["foliage"])
    alb = atlas.mat_albedo
    expect = np.where(inside < 0.0, alb[M["asphalt"]] * atlas.sample(np.full(5000, M["asphalt"]), xy[:, 0],
                                                                         xy[:, 1], fp),
                      alb[verge] * atlas.sample(verge, xy[:, 0], xy[:, 1], fp))
    expect = np.where((inside > -EDGE_LINE[1]) & (inside < -EDGE_LINE[0]), alb[M["marking"]], expect)
    expect = np.where((inside >= 0.0) & (inside < 0.25),
                      alb[M["kerb"]] * atlas.sample(np.full(5000, M["kerb"]), xy[:, 0], xy[:, 1], fp), expect)
    assert np.array_equal(r._ground(xy, xy[:, 0], xy[:, 1], fp), expect.astype(np.float32))
    assert {z.verge for z in ZONES} == {"pavement", "grass"} and ZONES[0].verge == "pavement"


def test_bad_ground_settings_name_the_field():
    with pytest.raises(SynthError, match="scenery.ground.dash_m"):
        dataclasses.replace(REALISTIC_GROUND, dash_m=(3.0, 3.0, 6.0)).check()
    with pytest.raises(SynthError, match="scenery.ground.texture_contrast"):
        dataclasses.replace(REALISTIC_SCENERY, ground=dataclasses.replace(REALISTIC_GROUND,
                                                                          texture_contrast=-1.0)).check()
