"""The twins' realistic scenery (plvo_synth.twin.scenery_realism): leafy crowns that scatter and pass lidar
rays, rows of houses of one design, railings, plain walls; the ideal world as it was; the realistic world the
same whichever way the road is driven. Small worlds built on the fly (a 160 m road), no twin is written."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from plvo.errors import SynthError
from plvo_synth.facade import facade_rectangles
from plvo_synth.mesh import MeshBuilder, Town
from plvo_synth.textures import MATERIAL_ID, MATERIALS, build_atlas
from plvo_synth.twin import shapes
from plvo_synth.twin.layout import ZONES, Layout
from plvo_synth.twin.scenery import build_world
from plvo_synth.twin.scenery_realism import IDEAL_SCENERY, REALISTIC_SCENERY, SceneryRealism

M = MATERIAL_ID
SEED = 2
SPEED = 6.0  # m/s: with SEED, city blocks and residential streets along the road


def _road(reverse: bool = False) -> np.ndarray:
    s = np.arange(0.0, 160.0, 1.0)
    road = np.column_stack([s, 8.0 * np.sin(s / 40.0), 0.02 * s])
    return road[::-1] if reverse else road


def _layout(reverse: bool = False) -> Layout:
    road = _road(reverse)
    return Layout(road, road, np.full(len(road), SPEED), SEED)


@pytest.fixture(scope="module")
def realistic() -> tuple[Town, int, dict]:
    return build_world(_layout(), SEED, REALISTIC_SCENERY)


def _cast(town: Town, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles))  # type: ignore[call-overload]
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()


def _one_tree(leaf_density: float) -> tuple[Town, np.ndarray, np.ndarray]:
    """A tree at the origin -> its Town, and the leaves' bounding box (lo, hi) (the blob's, when closed)."""
    b = MeshBuilder()
    shapes.tree(b, (0.0, 0.0), 0.0, np.random.default_rng(7), scale=1.0, leaf_density=leaf_density)
    town = b.build()
    crown = town.tri_material == (M["leaf"] if leaf_density > 0 else M["foliage"])
    pts = town.vertices[town.triangles[crown].astype(np.int64)].reshape(-1, 3)
    return town, pts.min(axis=0), pts.max(axis=0)


def test_lidar_rays_into_a_crown_scatter_through_its_depth_and_some_pass():
    """A fan of horizontal rays (0.18 deg apart, as an HDL-64E's columns) from 10 m across a leafy crown's middle:
    the returns spread through the crown's depth, neighbours differ by more than 0.5 m at many of them (KITTI's
    foliage signature), and some rays cross the crown untouched; a closed blob returns from its front surface."""
    results = {}
    for density in (REALISTIC_SCENERY.crown_leaf_density, 0.0):
        town, lo, hi = _one_tree(density)
        mid = 0.5 * (lo + hi)
        az = np.radians(np.arange(-12.0, 12.0, 0.18))
        origins = np.tile([-10.0, 0.0, mid[2]], (len(az), 1))
        dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros(len(az))])
        y_at_crown = 10.0 * np.tan(az)
        aimed = np.abs(y_at_crown) < 0.6 * 0.5 * (hi[1] - lo[1])  # rays through the crown's middle
        t = _cast(town, origins, dirs)[aimed]
        hit = np.isfinite(t)
        x = -10.0 + t[hit] * np.cos(az[aimed][hit])
        both = np.isfinite(t[1:]) & np.isfinite(t[:-1])
        jumps = np.abs(t[1:][both] - t[:-1][both]) > 0.5
        results[density] = (hit.mean(), x, jumps.mean(), lo, hi)
    pass_share, x, jump_share, lo, hi = results[REALISTIC_SCENERY.crown_leaf_density]
    assert 0.03 <= 1.0 - pass_share <= 0.6, pass_share  # some rays pass through, most are stopped
    assert lo[0] - 0.05 <= x.min() and x.max() <= hi[0] + 0.05  # every return within the crown's extent
    assert x.std() > 0.4 and x.max() - x.min() > 0.4 * (hi[0] - lo[0]), (x.std(), x.min(), x.max(), lo, hi)
    assert jump_share > 0.1, jump_share
    blob_pass, blob_x, blob_jumps, blob_lo, _ = results[0.0]
    assert blob_pass == 1.0 and blob_x.std() < 0.25 and blob_jumps == 0.0
    assert blob_x.max() < 0.5 * (blob_lo[0] + 0.0)  # the blob: its near half only


def test_leaves_hold_the_set_leaf_area_density():
    b = MeshBuilder()
    rng = np.random.default_rng(3)
    size, density, side = 0.22, 1.5, 6.0
    shapes.leaves(b, shapes._uniform_in_box(rng, np.zeros(3), np.full(3, side), density, size), size, rng,
                  M["leaf"], 1.0)
    town = b.build()
    tri = town.vertices[town.triangles.astype(np.int64)].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.sum() / side**3 == pytest.approx(density, rel=0.06)
    normals = town.tri_normal
    assert np.abs(normals.mean(axis=0)).max() < 0.05  # facing every way
    assert area.std() / area.mean() > 0.3  # leaves of many sizes


def test_ideal_world_is_the_world_before_the_realism():
    """IDEAL_SCENERY builds what build_world built before SceneryRealism existed: these counts, triangle sums and
    per-material counts were taken from that code on this layout."""
    town, n_ground, counts = build_world(_layout(), SEED, IDEAL_SCENERY)
    assert len(town.triangles) == 85024 and n_ground == 70370
    assert counts == {"building": 78, "wall": 38, "fence": 75, "hedge": 16, "parked": 47, "lamp": 39, "sign": 7,
                      "pole": 0, "tree": 55}
    mats = {int(k): int(v) for k, v in enumerate(np.bincount(town.tri_material)) if v}
    assert mats == {0: 70370, 3: 250, 4: 314, 5: 440, 6: 156, 7: 490, 8: 3310, 9: 564, 10: 376, 11: 1880,
                    12: 2300, 13: 4560, 15: 2, 16: 12}
    np.testing.assert_allclose(town.vertices.astype(np.float64).sum(axis=0), [5589770.9, 327582.8, 155371.5],
                               atol=0.5)


def test_realistic_world_keeps_the_ideal_objects_and_adds_what_is_hard(realistic):
    town, n_ground, counts = realistic
    ideal = build_world(_layout(), SEED, IDEAL_SCENERY)
    assert n_ground == ideal[1]
    ground = town.triangles[:n_ground].astype(np.int64)
    ideal_ground = ideal[0].triangles[:n_ground].astype(np.int64)
    np.testing.assert_array_equal(town.vertices[ground], ideal[0].vertices[ideal_ground])
    for kind, n in ideal[2].items():  # placed as before (a row's houses, of other sizes, move a few others)
        assert abs(counts[kind] - n) <= 0.1 * n + 1, (kind, counts[kind], n)
    assert counts["shrub"] > 10
    mats = np.bincount(town.tri_material, minlength=len(MATERIALS))
    assert mats[M["foliage"]] == 0  # no closed blob or hedge box is left
    assert mats[M["leaf"]] > 20 * (counts["tree"] + counts["hedge"])
    assert mats[M["plain_wall"]] > 0


def _fronts(town: Town) -> np.ndarray:
    """Every building's front facade row (each building adds front, side, back, side)."""
    return town.facades[0::4]


def test_rows_of_houses_share_one_window_layout(realistic):
    fronts = _fronts(realistic[0])
    same = np.all(fronts[:, None, :] == fronts[None, :, :], axis=2)
    np.fill_diagonal(same, False)
    repeated = np.flatnonzero(same.any(axis=1))
    assert len(repeated) >= 6, len(repeated)  # several rows of at least two houses
    a, b = repeated[0], np.flatnonzero(same[repeated[0]])[0]
    rects = facade_rectangles(fronts[a])
    assert len(rects) >= 2
    np.testing.assert_array_equal(rects, facade_rectangles(fronts[b]))  # window for window
    ideal_fronts = _fronts(build_world(_layout(), SEED, IDEAL_SCENERY)[0])
    ideal_same = np.all(ideal_fronts[:, None, :] == ideal_fronts[None, :, :], axis=2)
    assert ideal_same.sum() == len(ideal_fronts)  # before: every front its own


def test_railings_repeat_one_element():
    b = MeshBuilder()
    spacing = REALISTIC_SCENERY.picket_spacing_m
    shapes.fence(b, (0.0, 0.0), (5.8, 0.0), 0.0, np.random.default_rng(1), picket_spacing=spacing)
    town = b.build()
    tri = town.vertices[town.triangles.astype(np.int64)]
    low = tri[:, :, 2].max(axis=1) > 0.96  # pickets and bars reach above the top rail (0.95-1.05 m)
    thin = np.ptp(tri[:, :, 0], axis=1) < 0.1
    xs = np.unique(np.round(tri[low & thin][:, :, 0].mean(axis=1), 2))
    centres = np.unique(np.round(xs / spacing - 0.5))  # picket k stands at (k + 0.5) * 5.8 / n
    n = int(5.8 / spacing)
    assert len(centres) >= n - 1, (len(centres), n)


def test_plain_walls_have_only_faint_texture():
    atlas = build_atlas(0)
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 20, 5000), rng.uniform(0, 20, 5000)
    fine = np.full(5000, 0.02, np.float32)

    def spread(name: str) -> float:
        tex = atlas.sample(np.full(5000, M[name]), u, v, fine)
        return float(tex.std() / tex.mean())

    assert spread("plain_wall") < 0.05 and spread("barrier") < 0.05
    assert spread("plaster") > 0.1 and spread("brick") > 0.1


def test_realistic_scenery_does_not_depend_on_the_driving_direction(realistic):
    back = build_world(_layout(reverse=True), SEED, REALISTIC_SCENERY)

    def canon(town: Town) -> np.ndarray:
        return np.sort(np.round(town.vertices[town.triangles.astype(np.int64)], 3).reshape(-1, 9), axis=0)

    fwd = realistic[0]
    assert realistic[2] == back[2]
    assert len(fwd.triangles) == len(back[0].triangles) > 150_000
    np.testing.assert_allclose(canon(fwd), canon(back[0]), atol=2e-3)


def test_zones_of_the_test_road():
    assert {ZONES[z].name for z in np.unique(_layout().zone)} == {"city", "residential"}


@pytest.mark.parametrize("bad, field", [
    (SceneryRealism(crown_leaf_density=-1.0), "crown_leaf_density"),
    (SceneryRealism(plain_wall_share=1.5), "plain_wall_share"),
    (SceneryRealism(leaf_size_m=0.0), "leaf_size_m"),
    (SceneryRealism(shrub_p=(0.1, 0.2, 0.3)), "shrub_p"),  # type: ignore[arg-type]
])
def test_bad_scenery_settings_name_the_field(bad, field):
    with pytest.raises(SynthError, match=f"scenery.{field} ="):
        build_world(_layout(), SEED, bad)
