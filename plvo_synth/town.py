"""The procedural town: city blocks with raised pavements, rows of buildings, street furniture and road paint.

Only blocks within VIEW_RADIUS_M of the route are built. Each block draws from its own random stream
(seed, block index), so a block looks the same whatever route brings the car past it.
"""

from __future__ import annotations

import numpy as np

from plvo_synth import props
from plvo_synth.facade import GROUND_H, random_facade
from plvo_synth.mesh import MeshBuilder, Town
from plvo_synth.path import GRID_HALF, ROAD_HALF_WIDTH_M, StreetGrid
from plvo_synth.textures import MATERIAL_ID

M = MATERIAL_ID
VIEW_RADIUS_M = 150.0  # the lidar sees 80 m; the camera sees buildings further down the street
SIDEWALK_M = 3.5
CORNER_SKIP_M = 17.0  # rows along y start this far in, clear of the rows along x (buildings <= 16 m deep)
KERB_H = props.KERB_H
# a row of buildings along a block's side: (start, along t, inward n, length, street-facing wall, skip at its ends)
_Row = tuple[np.ndarray, np.ndarray, np.ndarray, float, int, float]


def blocks_near(grid: StreetGrid, route_xy: np.ndarray, radius: float = VIEW_RADIUS_M) -> list[tuple[int, int]]:
    """Blocks (i, j) (between streets i, i+1 and j, j+1) within `radius` of any (N,2) route point."""
    lo, hi = route_xy.min(axis=0) - radius, route_xy.max(axis=0) + radius
    ii = np.arange(np.searchsorted(grid.xs, lo[0]) - 1, np.searchsorted(grid.xs, hi[0]) + 1) - GRID_HALF
    jj = np.arange(np.searchsorted(grid.ys, lo[1]) - 1, np.searchsorted(grid.ys, hi[1]) + 1) - GRID_HALF
    out = []
    for i in ii:
        for j in jj:
            x0, x1, y0, y1 = grid.x(i), grid.x(i + 1), grid.y(j), grid.y(j + 1)
            dx = np.maximum(np.maximum(x0 - route_xy[:, 0], route_xy[:, 0] - x1), 0.0)
            dy = np.maximum(np.maximum(y0 - route_xy[:, 1], route_xy[:, 1] - y1), 0.0)
            if np.min(np.hypot(dx, dy)) < radius:
                out.append((int(i), int(j)))
    return out


def _rows(x0: float, x1: float, y0: float, y1: float) -> list[_Row]:
    """The four building rows of a block: (start, along t, inward n, length, index of the street-facing wall)."""
    e = ROAD_HALF_WIDTH_M + SIDEWALK_M
    lx, ly = x1 - x0 - 2 * e, y1 - y0 - 2 * e
    return [
        (np.array([x0 + e, y0 + e]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), lx, 0, 0.0),
        (np.array([x1 - e, y1 - e]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), lx, 2, 0.0),
        (np.array([x0 + e, y1 - e]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), ly, 3, CORNER_SKIP_M),
        (np.array([x1 - e, y0 + e]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), ly, 1, CORNER_SKIP_M),
    ]


def _building(b: MeshBuilder, a: np.ndarray, t: np.ndarray, n: np.ndarray, u0: float, u1: float, wall: int,
              rng: np.random.Generator) -> None:
    setback = 0.0 if rng.random() < 0.5 else rng.uniform(0.5, 4.0)
    depth, height = rng.uniform(10.0, 16.0), rng.uniform(6.0, 24.0)
    p0, p1 = a + u0 * t + setback * n, a + u1 * t + (setback + depth) * n
    lo = np.array([*np.minimum(p0, p1), KERB_H])
    hi = np.array([*np.maximum(p0, p1), KERB_H + height])
    front = random_facade(rng, u1 - u0, height)
    side = random_facade(rng, depth, height, like=front)
    facades = [-1] * 4
    facades[wall] = b.add_facade(front)
    facades[(wall + 1) % 4] = b.add_facade(side)
    facades[(wall + 3) % 4] = b.add_facade(side)
    material = M["brick"] if rng.random() < 0.4 else M["plaster"]
    b.add_box(lo, hi, material, rng.uniform(0.7, 1.25), facades=facades, top_material=M["roof"])
    wall_line = a + setback * n
    ledges = []
    if rng.random() < 0.6 and height > front[GROUND_H] + 1.0:
        ledges.append((KERB_H + front[GROUND_H] - 0.1, KERB_H + front[GROUND_H] + 0.15, 0.25))
    if rng.random() < 0.7:
        ledges.append((hi[2] - 0.45, hi[2] + 0.05, 0.35))
    for z0, z1, out in ledges:
        q0, q1 = wall_line + u0 * t - out * n, wall_line + u1 * t + 0.02 * n
        b.add_box([*np.minimum(q0, q1), z0], [*np.maximum(q0, q1), z1], M["ledge"], rng.uniform(0.8, 1.1))


def _row_buildings(b: MeshBuilder, row: _Row, rng: np.random.Generator) -> None:
    a, t, n, length, wall, skip = row
    u = skip
    while u < length - skip - 6.0:
        if rng.random() < 0.15:
            u += rng.uniform(3.0, 10.0)  # a gap: side walls and the back of the block show
            continue
        w = min(rng.uniform(8.0, 22.0), length - skip - u)
        if w < 6.0:
            break
        _building(b, a, t, n, u, u + w, wall, rng)
        u += w


def _row_furniture(b: MeshBuilder, row: _Row, rng: np.random.Generator) -> None:
    a, t, n, length, _, _ = row
    kerb = a - SIDEWALK_M * n  # the kerb line, in row coordinates u along t
    lamps = np.arange(10.0, length - 8.0, rng.uniform(25.0, 35.0))
    for u in lamps:
        props.lamp_post(b, kerb + u * t + 0.5 * n, n, rng)
    if rng.random() < 0.5:
        for u in np.arange(rng.uniform(4.0, 9.0), length - 4.0, rng.uniform(8.0, 14.0)):
            if np.min(np.abs(lamps - u), initial=99.0) > 2.5:
                props.tree(b, kerb + u * t + 2.0 * n, rng)
    if rng.random() < 0.5:
        props.sign_post(b, kerb + 4.0 * t + 0.9 * n, -t, rng)  # traffic along this kerb drives along -t
    if rng.random() < 0.6:
        for u in np.arange(14.0 - SIDEWALK_M, length + SIDEWALK_M - 14.0, rng.uniform(6.0, 7.5)):
            if rng.random() < 0.7:
                props.parked_car(b, kerb + u * t - 1.2 * n, t, rng)


def _block(b: MeshBuilder, x0: float, x1: float, y0: float, y1: float, rng: np.random.Generator) -> None:
    r = ROAD_HALF_WIDTH_M
    b.add_box([x0 + r, y0 + r, 0.0], [x1 - r, y1 - r, KERB_H], M["kerb"], 1.0, top_material=M["pavement"])
    for row in _rows(x0, x1, y0, y1):
        _row_buildings(b, row, rng)
        _row_furniture(b, row, rng)


def build_town(grid: StreetGrid, route_xy: np.ndarray, seed: int) -> Town:
    """(N,2) route points in the town frame -> the Town around them (deterministic for the seed)."""
    b = MeshBuilder()
    blocks = blocks_near(grid, route_xy)
    legs: set[tuple] = set()
    for i, j in blocks:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 2, i + GRID_HALF, j + GRID_HALF]))
        _block(b, grid.x(i), grid.x(i + 1), grid.y(j), grid.y(j + 1), rng)
        legs |= {("x", i, j), ("x", i, j + 1), ("y", i, j), ("y", i + 1, j)}
    for kind, i, j in sorted(legs):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 3 if kind == "x" else 4, i + GRID_HALF,
                                                            j + GRID_HALF]))
        a = (grid.x(i), grid.y(j))
        e = (grid.x(i + 1), grid.y(j)) if kind == "x" else (grid.x(i), grid.y(j + 1))
        props.street_paint(b, a, e, ROAD_HALF_WIDTH_M, rng)
    xs = [grid.x(i) for i, _ in blocks] + [grid.x(i + 1) for i, _ in blocks]
    ys = [grid.y(j) for _, j in blocks] + [grid.y(j + 1) for _, j in blocks]
    lo, hi = np.array([min(xs), min(ys)]) - 100.0, np.array([max(xs), max(ys)]) + 100.0
    b.add_quad([lo[0], lo[1], 0.0], [hi[0] - lo[0], 0, 0], [0, hi[1] - lo[1], 0], M["asphalt"], 1.0,
               origin=[0.0, 0.0, 0.0])
    return b.build()
