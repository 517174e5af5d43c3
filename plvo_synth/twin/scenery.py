"""The static world of a twin: the ground (one height field, road and verge told apart when shading) and the
scenery along both sides of every road.

Each kind of object has a world lattice of cells; a cell's own random stream (seed, kind, cell) proposes one
object, which is pushed out to its distance from the nearest road, turned to face it, and kept if it stands clear
of every road and of what is already placed (cells in lattice order). Nothing depends on the driving order, so a
revisit in either direction passes the same houses, trees and parked cars.

How hard the scenery is (leafy crowns and hedges, plain walls, rows of houses of one design, railings) follows a
SceneryRealism (twin.scenery_realism). Its choices come from streams of their own, keyed by the cell or by the
ROW square of cells, so they too are the same whichever way the car drives; IDEAL_SCENERY draws nothing extra
and builds the world as it was before them, triangle for triangle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from plvo_synth.mesh import MeshBuilder, Town
from plvo_synth.textures import MATERIAL_ID
from plvo_synth.twin import shapes
from plvo_synth.twin.layout import ZONE_ID, ZONES, Layout, Zone
from plvo_synth.twin.scenery_realism import REALISTIC_SCENERY, SceneryRealism

log = logging.getLogger(__name__)
M = MATERIAL_ID
GROUND_STEP_M = 2.0
GROUND_RADIUS_M = 110.0  # ground is meshed this far from a road (the lidar reaches 80-90 m)
OCC_RES_M = 0.5
ROW_TAG, DESIGN_TAG, PLAIN_TAG, RAILING_TAG = 141, 142, 143, 144  # the realism's streams (kinds use 41-49)


@dataclass(frozen=True)
class Kind:
    """One kind of object: its lattice spacing, its distance band behind the road edge, and its tag."""

    name: str
    tag: int
    spacing: float
    offset: tuple[float, float]  # metres beyond the road edge (negative: on the road, as parked cars)


KINDS = (
    Kind("building", 41, 9.0, (0.0, 25.0)),
    Kind("wall", 42, 6.0, (0.6, 1.2)),
    Kind("fence", 43, 6.0, (1.5, 3.0)),
    Kind("hedge", 44, 6.0, (1.5, 3.0)),
    Kind("parked", 45, 6.5, (-1.1, -1.1)),
    Kind("lamp", 46, 30.0, (0.6, 0.6)),
    Kind("sign", 47, 45.0, (0.9, 0.9)),
    Kind("pole", 48, 40.0, (1.5, 4.0)),
    Kind("tree", 49, 9.0, (2.0, 14.0)),
)
# Bushes are placed after every other kind (only with a SceneryRealism that asks for them), so they take the room
# that is left and every object of the ideal world stands where it stood.
SHRUB = Kind("shrub", 50, 5.0, (0.3, 9.0))


class _Occupancy:
    """A raster of what the placed objects cover, to keep new ones off them."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.lo = lo
        self.shape = tuple(np.ceil((hi - lo) / OCC_RES_M).astype(int) + 1)
        self.grid = np.zeros(self.shape, bool)

    def _cells(self, corners: np.ndarray, pad: float) -> tuple[np.ndarray, np.ndarray]:
        c = corners.mean(axis=0)
        grown = c + (corners - c) * (1.0 + pad / max(float(np.linalg.norm(corners[0] - c)), 1e-6))
        a, e1, e3 = grown[0], grown[1] - grown[0], grown[3] - grown[0]
        n1 = max(2, int(np.linalg.norm(e1) / (0.5 * OCC_RES_M)) + 2)
        n3 = max(2, int(np.linalg.norm(e3) / (0.5 * OCC_RES_M)) + 2)
        w1, w3 = np.meshgrid(np.linspace(0, 1, n1), np.linspace(0, 1, n3))
        pts = a + w1.reshape(-1, 1) * e1 + w3.reshape(-1, 1) * e3
        ij = np.floor((pts - self.lo) / OCC_RES_M).astype(int)
        ok = (ij >= 0).all(axis=1) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] < self.shape[1])
        return ij[ok, 0], ij[ok, 1]

    def free(self, corners: np.ndarray, pad: float = 0.3) -> bool:
        i, j = self._cells(corners, pad)
        return not self.grid[i, j].any()

    def take(self, corners: np.ndarray) -> None:
        i, j = self._cells(corners, 0.0)
        self.grid[i, j] = True


def _ground(b: MeshBuilder, layout: Layout) -> int:
    """Mesh the ground within GROUND_RADIUS_M of any road; returns its triangle count (they come first)."""
    lo = np.floor((layout.lo - GROUND_RADIUS_M) / GROUND_STEP_M) * GROUND_STEP_M
    hi = np.ceil((layout.hi + GROUND_RADIUS_M) / GROUND_STEP_M) * GROUND_STEP_M
    xs = np.arange(lo[0], hi[0] + 1e-9, GROUND_STEP_M)
    ys = np.arange(lo[1], hi[1] + 1e-9, GROUND_STEP_M)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    centres = np.column_stack([(gx[:-1, :-1] + 0.5 * GROUND_STEP_M).ravel(),
                               (gy[:-1, :-1] + 0.5 * GROUND_STEP_M).ravel()])
    d, _ = layout.nearest(centres, upper=GROUND_RADIUS_M + GROUND_STEP_M)
    keep = np.flatnonzero(np.isfinite(d))
    ni, nj = len(xs), len(ys)
    ci, cj = keep // (nj - 1), keep % (nj - 1)
    used = np.zeros((ni, nj), bool)
    for di in (0, 1):
        for dj in (0, 1):
            used[ci + di, cj + dj] = True
    vid = np.full((ni, nj), -1, np.int64)
    vid[used] = np.arange(int(used.sum()))
    vxy = np.column_stack([gx[used], gy[used]])
    vz = layout.height(vxy)
    verts = np.column_stack([vxy, vz])
    v00, v10, v11, v01 = vid[ci, cj], vid[ci + 1, cj], vid[ci + 1, cj + 1], vid[ci, cj + 1]
    tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    # Texture frame: world x, y (the renderer shades the ground from the hit position, see twin.render).
    frames = np.tile(np.array([0.0, 0, 0, 1, 0, 0, 0, 1, 0]), (len(tris), 1))
    b.add_triangles(verts, tris, frames, M["asphalt"])
    return len(tris)


def _lattice(layout: Layout, kind: Kind, seed: int) -> list[tuple[int, int]]:
    """Cells (ix, iy) of kind's lattice whose seeded point lies within reach of a road's object band."""
    reach = max(ZONES, key=lambda z: z.half_width).half_width + kind.offset[1] + kind.spacing
    lo = np.floor((layout.lo - reach) / kind.spacing).astype(int)
    hi = np.ceil((layout.hi + reach) / kind.spacing).astype(int)
    ix, iy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    centres = (np.column_stack([ix.ravel(), iy.ravel()]) + 0.5) * kind.spacing
    d, _ = layout.nearest(centres, upper=reach)
    ok = np.isfinite(d)
    return [(int(a), int(c)) for a, c in zip(ix.ravel()[ok], iy.ravel()[ok])]


def _proposal(layout: Layout, kind: Kind, seed: int, ix: int, iy: int
              ) -> tuple[np.random.Generator, Zone, int, np.ndarray] | None:
    """A cell's proposal: (rng, zone, road sample index, unit vector road->object, base point on the road edge)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, kind.tag, ix + (1 << 20), iy + (1 << 20)]))
    q = (np.array([ix, iy]) + rng.uniform(0.0, 1.0, 2)) * kind.spacing
    d, ks = layout.nearest(q)
    k = int(ks[0])
    away = q - layout.xy[k]
    norm = float(np.linalg.norm(away))
    if norm < 1e-6:
        return None
    return rng, ZONES[layout.zone[k]], k, away / norm


def _stream(seed: int, tag: int, ix: int, iy: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, tag, ix + (1 << 20), iy + (1 << 20)]))


@dataclass(frozen=True)
class _Look:
    """How one proposal looks beyond where it stands: the stream its design is drawn from, plain walls, railing."""

    design: np.random.Generator
    plain: bool
    railing: bool


def _look(seed: int, kind: Kind, ix: int, iy: int, rng: np.random.Generator, scenery: SceneryRealism) -> _Look:
    """A building in a row square (scenery.row_m) drawn as a row draws its design from the square's own stream
    (every house of the row the same sizes, windows and walls); anything else from its cell's."""
    plain = kind.name in ("building", "wall") and scenery.plain_wall_share > 0 \
        and _stream(seed, PLAIN_TAG, ix, iy).random() < scenery.plain_wall_share
    railing = kind.name == "fence" and scenery.railing_share > 0 \
        and _stream(seed, RAILING_TAG, ix, iy).random() < scenery.railing_share
    if kind.name == "building" and scenery.facade_row_share > 0:
        bx, by = (int(np.floor((c + 0.5) * kind.spacing / scenery.row_m)) for c in (ix, iy))
        square = _stream(seed, ROW_TAG, bx, by)
        if square.random() < scenery.facade_row_share:
            return _Look(_stream(seed, DESIGN_TAG, bx, by), bool(square.random() < scenery.plain_wall_share), False)
    return _Look(rng, bool(plain), bool(railing))


def _place(b: MeshBuilder, layout: Layout, occ: _Occupancy, kind: Kind, seed: int, scenery: SceneryRealism) -> int:
    placed = 0
    for ix, iy in _lattice(layout, kind, seed):
        prop = _proposal(layout, kind, seed, ix, iy)
        if prop is None:
            continue
        rng, zone, k, away = prop
        if _one(b, layout, occ, kind, rng, zone, k, away, _look(seed, kind, ix, iy, rng, scenery), scenery):
            placed += 1
    return placed


def _clear(layout: Layout, corners: np.ndarray, margin: float) -> bool:
    """Every footprint point at least `margin` beyond every road edge."""
    c = corners.mean(axis=0)
    pts = np.concatenate([corners, c[None], 0.5 * (corners + np.roll(corners, -1, axis=0))])
    return bool(layout.clearance(pts).min() >= margin)


def _one(b: MeshBuilder, layout: Layout, occ: _Occupancy, kind: Kind, rng: np.random.Generator, zone: Zone, k: int,
         away: np.ndarray, look: _Look, scenery: SceneryRealism) -> bool:
    edge = layout.xy[k] + away * layout.half_width[k]  # the road edge on this side
    tangent = layout.tangent[k]
    if tangent[0] < 0.0 or (tangent[0] == 0.0 and tangent[1] < 0.0):
        tangent = -tangent  # the way the car drove past must not matter
    yaw = float(np.arctan2(tangent[1], tangent[0]))
    name = kind.name
    p_of = {"building": zone.building_p, "wall": zone.wall_p, "fence": zone.fence_p, "hedge": zone.hedge_p,
            "parked": zone.parked_p, "lamp": zone.lamp_p, "sign": zone.sign_p, "pole": zone.pole_p,
            "tree": zone.tree_p, "shrub": scenery.shrub_p[ZONE_ID[zone.name]]}
    if rng.random() >= p_of[name]:
        return False
    if name == "building":
        design = look.design
        w, dp, h = design.uniform(*zone.width), design.uniform(*zone.depth), design.uniform(*zone.height)
        setback = design.uniform(*zone.setback)
        c = edge + away * (setback + 0.5 * dp + (3.0 if zone.verge == "pavement" else 0.5))
        # wall 0 faces -n of the heading: choose the heading whose left normal points away from the road
        n = np.array([-tangent[1], tangent[0]])
        yaw_b = yaw if n @ away > 0 else yaw + np.pi
        corners = shapes.box_corners(c, yaw_b, w, dp)
        if not (_clear(layout, corners, 1.0) and occ.free(corners, 0.5)):
            return False
        z0 = float(layout.height(corners).min()) - 0.3
        shapes.building(b, c, yaw_b, w, dp, h + 0.3, z0, design, look.plain)
        occ.take(corners)
        return True
    off = rng.uniform(*kind.offset)
    p = edge + away * off
    if name in ("wall", "fence", "hedge"):
        length = kind.spacing - 0.2
        corners = shapes.box_corners(p, yaw, length, 0.6)
        if not (_clear(layout, corners, 0.3) and occ.free(corners, 0.1)):
            return False
        a, e = p - 0.5 * length * tangent, p + 0.5 * length * tangent
        z0 = float(layout.height(p[None])[0])
        if name == "wall":
            plain = (M["barrier"] if zone.name == "highway" else M["plain_wall"]) if look.plain else None
            shapes.wall(b, a, e, z0, rng.uniform(1.5, 3.0) if zone.name == "highway" else rng.uniform(1.0, 2.0), rng,
                        plain)
        elif name == "fence":
            shapes.fence(b, a, e, z0, rng, scenery.picket_spacing_m if look.railing else 0.0)
        else:
            shapes.hedge(b, a, e, z0, rng, scenery.hedge_leaf_density, scenery.leaf_size_m)
        occ.take(corners)
        return True
    if name == "parked":
        corners = shapes.box_corners(p, yaw, 4.6, 2.0)
        # parked cars stand on the road's edge: clear of the driven lanes (>= 3.5 m from any path sample)
        d, kk = layout.nearest(corners)
        if (d < 4.6).any() or not occ.free(corners, 0.2):
            return False
        shapes.parked_car(b, p, yaw + (np.pi if rng.random() < 0.5 else 0.0), float(layout.height(p[None])[0]), rng)
        occ.take(corners)
        return True
    size = {"lamp": 0.5, "sign": 0.5, "pole": 0.6, "tree": 2.0, "shrub": 2.4}[name]
    corners = shapes.box_corners(p, yaw, size, size)
    if not (_clear(layout, corners, 0.2 if name not in ("tree", "shrub") else 0.5) and occ.free(corners, 0.1)):
        return False
    z0 = float(layout.height(p[None])[0])
    if name == "shrub":
        shapes.shrub(b, p, z0, rng, scenery.shrub_leaf_density, scenery.leaf_size_m)
    elif name == "lamp":
        shapes.lamp_post(b, p, -away, z0, rng)
    elif name == "sign":
        shapes.sign_post(b, p, -tangent if rng.random() < 0.5 else tangent, z0, rng)
    elif name == "pole":
        shapes.pole(b, p, z0, rng)
    else:
        shapes.tree(b, p, z0, rng, scale=1.0 if zone.name in ("city", "residential") else rng.uniform(1.0, 1.6),
                    leaf_density=scenery.crown_leaf_density, leaf_size=scenery.leaf_size_m)
    occ.take(corners)
    return True


def build_world(layout: Layout, seed: int, scenery: SceneryRealism = REALISTIC_SCENERY) -> tuple[Town, int, dict]:
    """The twin's static Town (ground triangles first), the ground's triangle count, and counts per kind; the
    scenery as hard as `scenery` says (IDEAL_SCENERY: the world as it was before those settings)."""
    scenery.check()
    b = MeshBuilder()
    n_ground = _ground(b, layout)
    occ = _Occupancy(layout.lo - 60.0, layout.hi + 60.0)
    counts = {}
    for kind in KINDS:
        counts[kind.name] = _place(b, layout, occ, kind, seed, scenery)
    if any(scenery.shrub_p):
        counts[SHRUB.name] = _place(b, layout, occ, SHRUB, seed, scenery)
    log.info("twin world: %d ground triangles; %s", n_ground, counts)
    return b.build(), n_ground, counts
