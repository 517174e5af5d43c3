"""Oriented building blocks of the twins' scenery: boxes at any heading, buildings with facades, street furniture.

The town's own props (plvo.data.synth.props) stand on a flat grid at z = 0 and along the axes; a twin's roads run
at any heading and height, so these take a centre (x, y), a heading `yaw` (the object's long axis, radians from +x)
and the ground height `z0` under them.
"""

from __future__ import annotations

import numpy as np

from plvo.data.synth.facade import GROUND_H, random_facade
from plvo.data.synth.mesh import EDGE_GEOMETRIC, MeshBuilder
from plvo.data.synth.props import _SPHERE
from plvo.data.synth.textures import MATERIAL_ID, SIGN_MATERIALS

M = MATERIAL_ID


def box_corners(c, yaw: float, length: float, width: float) -> np.ndarray:
    """(4,2) footprint corners counter-clockwise seen from above; length along yaw, width across."""
    t = np.array([np.cos(yaw), np.sin(yaw)])
    n = np.array([-t[1], t[0]])
    c = np.asarray(c, np.float64)[:2]
    hl, hw = 0.5 * length, 0.5 * width
    return np.array([c - hl * t - hw * n, c + hl * t - hw * n, c + hl * t + hw * n, c - hl * t + hw * n])


def oriented_box(b: MeshBuilder, c, yaw: float, length: float, width: float, z0: float, z1: float, material: int,
                 tint: float = 1.0, facades=(-1, -1, -1, -1), top: int | None = None, edges: bool = True) -> None:
    """A box without a bottom. Wall k runs from corner k to k+1 (box_corners order; wall 0 faces -n, where n is
    yaw turned left); facades[k] is a facade row or -1, its u along the wall from the left foot seen outside."""
    cs = box_corners(c, yaw, length, width)
    lo = np.column_stack([cs, np.full(4, z0)])
    hi = np.column_stack([cs, np.full(4, z1)])
    for k in range(4):
        a, e = lo[k], lo[(k + 1) % 4]
        b.add_quad(a, e - a, [0.0, 0.0, z1 - z0], material, tint, facade=facades[k])
        if facades[k] >= 0:
            b.add_facade_edges(a, e - a, facades[k])  # window and door outlines are ground-truth edges too
    b.add_quad(hi[0], hi[1] - hi[0], hi[3] - hi[0], material if top is None else top, tint, origin=hi[0])
    if edges:
        ring = [(lo[k], lo[(k + 1) % 4]) for k in range(4)] + [(hi[k], hi[(k + 1) % 4]) for k in range(4)]
        ring += [(lo[k], hi[k]) for k in range(4)]
        b.add_edges(np.array(ring), EDGE_GEOMETRIC)


def building(b: MeshBuilder, c, yaw: float, width: float, depth: float, height: float, z0: float,
             rng: np.random.Generator) -> None:
    """A building whose front (wall 0, facing -n) looks onto the road; width along yaw."""
    front = random_facade(rng, width, height)
    side = random_facade(rng, depth, height, like=front)
    back = random_facade(rng, width, height, like=front)
    fac = [b.add_facade(front), b.add_facade(side), b.add_facade(back), b.add_facade(side)]
    material = M["brick"] if rng.random() < 0.4 else M["plaster"]
    oriented_box(b, c, yaw, width, depth, z0, z0 + height, material, rng.uniform(0.7, 1.25), fac, M["roof"])
    if rng.random() < 0.6 and height > front[GROUND_H] + 1.0:  # a ledge over the ground floor, on the front
        t = np.array([np.cos(yaw), np.sin(yaw)])
        n = np.array([-t[1], t[0]])
        lc = np.asarray(c)[:2] - n * (0.5 * depth + 0.12)
        zl = z0 + front[GROUND_H]
        oriented_box(b, lc, yaw, width, 0.25, zl - 0.1, zl + 0.15, M["ledge"], rng.uniform(0.8, 1.1))


def tree(b: MeshBuilder, p, z0: float, rng: np.random.Generator, scale: float = 1.0) -> None:
    trunk_h = rng.uniform(2.2, 3.2) * scale
    oriented_box(b, p, rng.uniform(0, np.pi), 0.3 * scale, 0.3 * scale, z0 - 0.1, z0 + trunk_h + 0.5, M["bark"],
                 rng.uniform(0.7, 1.2))
    r, zs = rng.uniform(1.4, 2.3) * scale, rng.uniform(0.9, 1.3)
    verts, faces = _SPHERE
    lumps = verts * r * rng.uniform(0.85, 1.15, (len(verts), 1)) * np.array([1.0, 1.0, zs])
    centre = np.array([p[0], p[1], z0 + trunk_h + 0.9 * r * zs])
    b.add_blob(lumps + centre, faces, M["foliage"], rng.uniform(0.7, 1.2), centre)


def lamp_post(b: MeshBuilder, p, to_road, z0: float, rng: np.random.Generator) -> None:
    """A lamp post at p whose arm reaches towards the road (unit xy vector to_road)."""
    h = rng.uniform(6.0, 8.0)
    yaw = float(np.arctan2(to_road[1], to_road[0]))
    oriented_box(b, p, yaw, 0.18, 0.18, z0 - 0.1, z0 + h, M["metal"], rng.uniform(0.6, 1.2))
    q = np.asarray(p)[:2] + 0.8 * np.asarray(to_road)
    oriented_box(b, q, yaw, 1.6, 0.1, z0 + h - 0.1, z0 + h, M["metal"], 0.8)
    oriented_box(b, np.asarray(p)[:2] + 1.5 * np.asarray(to_road), yaw, 0.6, 0.3, z0 + h - 0.3, z0 + h - 0.1,
                 M["metal"], 1.8)


def pole(b: MeshBuilder, p, z0: float, rng: np.random.Generator) -> None:
    """A tall wooden or concrete pole (power line, highway light) with a cross arm."""
    h = rng.uniform(8.0, 10.0)
    yaw = rng.uniform(0, np.pi)
    oriented_box(b, p, yaw, 0.28, 0.28, z0 - 0.1, z0 + h, M["bark"] if rng.random() < 0.6 else M["kerb"], 1.0)
    oriented_box(b, p, yaw, 2.2, 0.14, z0 + h - 0.8, z0 + h - 0.6, M["bark"], 0.9)


def sign_post(b: MeshBuilder, p, facing, z0: float, rng: np.random.Generator) -> None:
    """A sign post at p whose plate's face looks along the unit xy vector `facing` (towards oncoming traffic)."""
    f = np.asarray(facing, np.float64)
    yaw = float(np.arctan2(f[1], f[0])) + np.pi / 2  # the plate's width runs across `facing`
    oriented_box(b, p, yaw, 0.08, 0.08, z0 - 0.1, z0 + 2.6, M["metal"], 0.9)
    size = 0.7
    c = np.asarray(p)[:2] + 0.06 * f
    oriented_box(b, c, yaw, size, 0.04, z0 + 2.3, z0 + 2.3 + size, M["metal"], 0.7)
    side = np.array([np.cos(yaw), np.sin(yaw)])
    front = c + 0.021 * f
    corner = np.array([*(front + side * size / 2), z0 + 2.3])
    mat = M[SIGN_MATERIALS[int(rng.integers(len(SIGN_MATERIALS)))]]
    b.add_quad(corner, [*(-side * size), 0.0], [0.0, 0.0, size], mat, 1.0)


def parked_car(b: MeshBuilder, c, yaw: float, z0: float, rng: np.random.Generator) -> None:
    tint = float(rng.choice([0.25, 0.5, 0.9, 1.3, 1.7]))
    oriented_box(b, c, yaw, 4.2, 1.8, z0 + 0.3, z0 + 1.0, M["car_paint"], tint)
    t = np.array([np.cos(yaw), np.sin(yaw)])
    n = np.array([-t[1], t[0]])
    cab = np.asarray(c)[:2] - t * rng.uniform(0.0, 0.3)
    oriented_box(b, cab, yaw, 2.3, 1.6, z0 + 1.0, z0 + 1.45, M["car_glass"], 1.0, top=M["car_paint"])
    for sa in (-1.4, 1.4):
        for sb in (-0.8, 0.8):
            oriented_box(b, np.asarray(c)[:2] + t * sa + n * sb, yaw, 0.64, 0.24, z0 - 0.05, z0 + 0.62, M["tyre"],
                         1.0, edges=False)


def fence(b: MeshBuilder, a, e, z0: float, rng: np.random.Generator) -> None:
    """A post-and-rail fence from a to e (xy)."""
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    length = float(np.linalg.norm(e - a))
    yaw = float(np.arctan2(*(e - a)[::-1]))
    mat = M["bark"] if rng.random() < 0.5 else M["metal"]
    for w in np.linspace(0.0, 1.0, max(2, int(length / 2.0) + 1)):
        oriented_box(b, a + w * (e - a), yaw, 0.1, 0.1, z0 - 0.1, z0 + 1.1, mat, 0.9, edges=False)
    mid = 0.5 * (a + e)
    for h in (0.45, 0.95):
        oriented_box(b, mid, yaw, length, 0.05, z0 + h, z0 + h + 0.1, mat, 1.0)


def hedge(b: MeshBuilder, a, e, z0: float, rng: np.random.Generator) -> None:
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    yaw = float(np.arctan2(*(e - a)[::-1]))
    oriented_box(b, 0.5 * (a + e), yaw, float(np.linalg.norm(e - a)), 0.9, z0 - 0.1, z0 + rng.uniform(1.0, 1.8),
                 M["foliage"], rng.uniform(0.6, 0.9), edges=False)


def wall(b: MeshBuilder, a, e, z0: float, height: float, rng: np.random.Generator) -> None:
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    yaw = float(np.arctan2(*(e - a)[::-1]))
    mat = M["kerb"] if rng.random() < 0.6 else M["brick"]
    oriented_box(b, 0.5 * (a + e), yaw, float(np.linalg.norm(e - a)), 0.3, z0 - 0.2, z0 + height, mat,
                 rng.uniform(0.8, 1.1))
