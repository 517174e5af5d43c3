"""Oriented building blocks of the twins' scenery: boxes at any heading, buildings with facades, street furniture.

The town's own props (plvo_synth.props) stand on a flat grid at z = 0 and along the axes; a twin's roads run
at any heading and height, so these take a centre (x, y), a heading `yaw` (the object's long axis, radians from +x)
and the ground height `z0` under them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from plvo_synth.facade import GROUND_H, random_facade
from plvo_synth.mesh import EDGE_GEOMETRIC, MeshBuilder
from plvo_synth.props import _SPHERE
from plvo_synth.textures import MATERIAL_ID, SIGN_MATERIALS

M = MATERIAL_ID
LEAF_SIZE_SIGMA = 0.3  # spread of leaf sizes (log-normal sigma)


def box_corners(c: npt.ArrayLike, yaw: float, length: float, width: float) -> np.ndarray:
    """(4,2) footprint corners counter-clockwise seen from above; length along yaw, width across."""
    t = np.array([np.cos(yaw), np.sin(yaw)])
    n = np.array([-t[1], t[0]])
    c = np.asarray(c, np.float64)[:2]
    hl, hw = 0.5 * length, 0.5 * width
    return np.array([c - hl * t - hw * n, c + hl * t - hw * n, c + hl * t + hw * n, c - hl * t + hw * n])


def oriented_box(b: MeshBuilder, c: npt.ArrayLike, yaw: float, length: float, width: float, z0: float, z1: float,
                 material: int, tint: float = 1.0, facades: Sequence[int] = (-1, -1, -1, -1), top: int | None = None,
                 edges: bool = True) -> None:
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


def building(b: MeshBuilder, c: np.ndarray, yaw: float, width: float, depth: float, height: float, z0: float,
             rng: np.random.Generator, plain: bool = False) -> None:
    """A building whose front (wall 0, facing -n) looks onto the road; width along yaw. plain: its walls are
    plain render (faint shading, windows as drawn) instead of brick or textured plaster. Every draw comes from
    `rng`, so two buildings of equal sizes drawn from equally seeded streams are one design."""
    front = random_facade(rng, width, height)
    side = random_facade(rng, depth, height, like=front)
    back = random_facade(rng, width, height, like=front)
    fac = [b.add_facade(front), b.add_facade(side), b.add_facade(back), b.add_facade(side)]
    material = M["brick"] if rng.random() < 0.4 else M["plaster"]
    if plain:
        material = M["plain_wall"]
    oriented_box(b, c, yaw, width, depth, z0, z0 + height, material, rng.uniform(0.7, 1.25), fac, M["roof"])
    if rng.random() < 0.6 and height > front[GROUND_H] + 1.0:  # a ledge over the ground floor, on the front
        t = np.array([np.cos(yaw), np.sin(yaw)])
        n = np.array([-t[1], t[0]])
        lc = np.asarray(c)[:2] - n * (0.5 * depth + 0.12)
        zl = z0 + front[GROUND_H]
        oriented_box(b, lc, yaw, width, 0.25, zl - 0.1, zl + 0.15, M["ledge"], rng.uniform(0.8, 1.1))


def tree(b: MeshBuilder, p: np.ndarray, z0: float, rng: np.random.Generator, scale: float = 1.0,
         leaf_density: float = 0.0, leaf_size: float = 0.22) -> None:
    """A trunk and a crown: a closed lumpy blob (leaf_density 0) or lobes of leaves (m^2 of leaf a m^3)."""
    trunk_h = rng.uniform(2.2, 3.2) * scale
    oriented_box(b, p, rng.uniform(0, np.pi), 0.3 * scale, 0.3 * scale, z0 - 0.1, z0 + trunk_h + 0.5, M["bark"],
                 rng.uniform(0.7, 1.2))
    r, zs = rng.uniform(1.4, 2.3) * scale, rng.uniform(0.9, 1.3)
    verts, faces = _SPHERE
    lumps = verts * r * rng.uniform(0.85, 1.15, (len(verts), 1)) * np.array([1.0, 1.0, zs])
    centre = np.array([p[0], p[1], z0 + trunk_h + 0.9 * r * zs])
    tint = rng.uniform(0.7, 1.2)
    if leaf_density <= 0.0:
        b.add_blob(lumps + centre, faces, M["foliage"], tint, centre)
        return
    lobes, radii = crown_lobes(centre, r, zs, rng)
    fork = np.array([p[0], p[1], z0 + trunk_h + 0.3])
    struts(b, np.repeat(fork[None], len(lobes), axis=0), lobes, 0.09 * scale, M["bark"], 0.8)
    _leaves_in_lobes(b, lobes, radii, zs, rng, leaf_density, leaf_size, tint)


def shrub(b: MeshBuilder, p: np.ndarray, z0: float, rng: np.random.Generator, leaf_density: float,
          leaf_size: float) -> None:
    """A bush at p: 3-6 lobes of leaves from the ground up to 1.2-3.5 m, 1.6-3.6 m across, round a few stems."""
    r, h = rng.uniform(0.8, 1.8), rng.uniform(1.2, 3.5)
    zs = 0.5 * h / r
    centre = np.array([p[0], p[1], z0 + 0.5 * h])
    n = int(rng.integers(3, 7))
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lobes = centre + d * (r * rng.uniform(0.2, 0.5, (n, 1))) * np.array([1.0, 1.0, zs])
    radii = r * rng.uniform(0.45, 0.65, n)
    base = np.array([p[0], p[1], z0 - 0.1])
    struts(b, np.repeat(base[None], n, axis=0), lobes, 0.05, M["bark"], 0.8)
    _leaves_in_lobes(b, lobes, radii, zs, rng, leaf_density, leaf_size, rng.uniform(0.6, 1.0), floor=z0)


def _leaves_in_lobes(b: MeshBuilder, lobes: np.ndarray, radii: np.ndarray, zs: float, rng: np.random.Generator,
                     leaf_density: float, leaf_size: float, tint: float, floor: float = -np.inf) -> None:
    """Leaves at leaf_density uniform in the union of ellipsoidal lobes (vertical scale zs), none below floor."""
    reach = radii[:, None] * np.array([1.0, 1.0, zs])
    lo = (lobes - reach).min(axis=0)
    lo[2] = max(lo[2], floor)
    pts = _uniform_in_box(rng, lo, (lobes + reach).max(axis=0), leaf_density, leaf_size)
    rel = (pts[:, None, :] - lobes[None]) / np.array([1.0, 1.0, zs])
    inside = (np.einsum("nkj,nkj->nk", rel, rel) < radii[None] ** 2).any(axis=1)
    leaves(b, pts[inside], leaf_size, rng, M["leaf"], tint)


def crown_lobes(centre: np.ndarray, r: float, zs: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A crown of radius r (height scale zs) as 6-11 lobes, the boughs' clumps: (L,3) centres and (L,) radii
    (horizontal; vertically times zs). The gaps between them let light and rays through and make the outline
    ragged, as a real crown's."""
    n = int(rng.integers(6, 12))
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] *= 0.7  # boughs spread sideways more than up and down
    lobes = centre + d * (r * rng.uniform(0.3, 0.75, (n, 1))) * np.array([1.0, 1.0, zs])
    return lobes, r * rng.uniform(0.32, 0.52, n)


def _uniform_in_box(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, density: float,
                    leaf_size: float) -> np.ndarray:
    """Leaf centres at `density` m^2 of leaf per m^3, uniform in the box lo-hi (to be cut to a shape)."""
    volume = float(np.prod(np.maximum(hi - lo, 0.0)))
    n = int(rng.poisson(density * volume / leaf_area(leaf_size)))
    return lo + rng.random((n, 3)) * (hi - lo)


def leaf_area(size: float) -> float:
    """Area of a leaf triangle of edge `size`."""
    return float(np.sqrt(3.0) / 4.0 * size * size)


def leaves(b: MeshBuilder, centres: np.ndarray, size: float, rng: np.random.Generator, material: int,
           tint: float) -> None:
    """Leaf triangles of typical edge `size` at (N,3) centres, facing every way (a spherical leaf-angle
    distribution), each of its own size and shape (their mean area that of an equilateral triangle of edge
    `size`: equal leaves would give equal corners, which real foliage does not) and showing its own patch of the
    material's tile."""
    n = len(centres)
    if not n:
        return
    normal = rng.standard_normal((n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    t = rng.standard_normal((n, 3))
    e1 = t - np.einsum("ij,ij->i", t, normal)[:, None] * normal
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-9)
    e2 = np.cross(normal, e1)
    ang = np.array([0.0, 2.0 * np.pi / 3.0, 4.0 * np.pi / 3.0]) + rng.uniform(-0.35, 0.35, (n, 3))
    # log-normal scale with E[scale^2] = 1, corner radii with mean 1: the mean area stays leaf_area(size)
    scale = np.exp(LEAF_SIZE_SIGMA * rng.standard_normal((n, 1)) - LEAF_SIZE_SIGMA**2)
    rc = size / np.sqrt(3.0) * scale * rng.uniform(0.7, 1.3, (n, 3))  # circumradius, corner by corner
    verts = centres[:, None, :] + rc[:, :, None] * (np.cos(ang)[:, :, None] * e1[:, None, :]
                                                    + np.sin(ang)[:, :, None] * e2[:, None, :])
    shift = rng.uniform(0.0, 3.0, (n, 2))  # texture origin: each leaf samples the tile somewhere else
    origin = centres - shift[:, :1] * e1 - shift[:, 1:] * e2
    frames = np.concatenate([origin, e1, e2], axis=1)
    b.add_triangles(verts.reshape(-1, 3), np.arange(3 * n).reshape(n, 3), frames, material, tint)


def struts(b: MeshBuilder, a: np.ndarray, e: np.ndarray, width: float, material: int, tint: float) -> None:
    """Square prisms of side `width` from (N,3) points a to e (boughs): four sides each, no caps."""
    a, e = np.asarray(a, np.float64), np.asarray(e, np.float64)
    axis = e - a
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    ax = axis / np.maximum(length, 1e-9)
    helper = np.where(np.abs(ax[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    p1 = np.cross(ax, helper)
    p1 /= np.linalg.norm(p1, axis=1, keepdims=True)
    p2 = np.cross(ax, p1)
    h = 0.5 * width
    ring = [h * (p1 + p2), h * (p1 - p2), h * (-p1 - p2), h * (-p1 + p2)]
    verts, frames = [], []
    for k in range(4):  # each side: corners a+ring[k], a+ring[k+1], e+ring[k+1], e+ring[k]
        c0, c1 = ring[k], ring[(k + 1) % 4]
        verts.append(np.stack([a + c0, a + c1, e + c1, e + c0], axis=1))
        across = (c1 - c0) / width
        frame = np.concatenate([a + c0, across, ax], axis=1)
        frames.append(np.repeat(frame, 2, axis=0).reshape(-1, 2, 9))
    v = np.stack(verts, axis=1).reshape(-1, 3)  # (N*4 sides*4 corners, 3)
    quads = np.arange(len(a) * 4)[:, None] * 4
    tris = np.concatenate([quads + [[0, 1, 2]], quads + [[0, 2, 3]]], axis=1).reshape(-1, 3)
    f = np.stack(frames, axis=1).reshape(-1, 9)
    b.add_triangles(v, tris, f, material, tint)


def prisms(b: MeshBuilder, centres: np.ndarray, yaw: float, length: float, width: float, z0: float, z1: float,
           material: int, tint: float) -> None:
    """Many equal upright boxes (pickets, bars) at (N,2) centres, one heading, four walls and a top each, in one
    batch of triangles (no ground-truth edges: like fence posts, too thin to count as lines)."""
    n = len(centres)
    if not n:
        return
    t = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    nn = np.array([-t[1], t[0], 0.0])
    base = np.column_stack([np.asarray(centres, np.float64)[:, :2], np.full(n, z0)])
    hl, hw = 0.5 * length, 0.5 * width
    foot = [base - hl * t - hw * nn, base + hl * t - hw * nn, base + hl * t + hw * nn, base - hl * t + hw * nn]
    up = np.array([0.0, 0.0, z1 - z0])
    verts, frames = [], []
    for k in range(4):
        c0, c1 = foot[k], foot[(k + 1) % 4]
        verts.append(np.stack([c0, c1, c1 + up, c0 + up], axis=1))
        along = (c1 - c0) / np.linalg.norm(c1[0] - c0[0])
        frames.append(np.concatenate([c0, along, np.broadcast_to([0.0, 0.0, 1.0], (n, 3))], axis=1))
    verts.append(np.stack([foot[0] + up, foot[1] + up, foot[2] + up, foot[3] + up], axis=1))
    frames.append(np.concatenate([foot[0] + up, np.broadcast_to(t, (n, 3)), np.broadcast_to(nn, (n, 3))], axis=1))
    v = np.stack(verts, axis=1).reshape(-1, 3)  # (N*5 quads*4 corners, 3)
    quads = np.arange(n * 5)[:, None] * 4
    tris = np.concatenate([quads + [[0, 1, 2]], quads + [[0, 2, 3]]], axis=1).reshape(-1, 3)
    f = np.repeat(np.stack(frames, axis=1).reshape(-1, 9), 2, axis=0)
    b.add_triangles(v, tris, f, material, tint)


def lamp_post(b: MeshBuilder, p: np.ndarray, to_road: np.ndarray, z0: float, rng: np.random.Generator) -> None:
    """A lamp post at p whose arm reaches towards the road (unit xy vector to_road)."""
    h = rng.uniform(6.0, 8.0)
    yaw = float(np.arctan2(to_road[1], to_road[0]))
    oriented_box(b, p, yaw, 0.18, 0.18, z0 - 0.1, z0 + h, M["metal"], rng.uniform(0.6, 1.2))
    q = np.asarray(p)[:2] + 0.8 * np.asarray(to_road)
    oriented_box(b, q, yaw, 1.6, 0.1, z0 + h - 0.1, z0 + h, M["metal"], 0.8)
    oriented_box(b, np.asarray(p)[:2] + 1.5 * np.asarray(to_road), yaw, 0.6, 0.3, z0 + h - 0.3, z0 + h - 0.1,
                 M["metal"], 1.8)


def pole(b: MeshBuilder, p: np.ndarray, z0: float, rng: np.random.Generator) -> None:
    """A tall wooden or concrete pole (power line, highway light) with a cross arm."""
    h = rng.uniform(8.0, 10.0)
    yaw = rng.uniform(0, np.pi)
    oriented_box(b, p, yaw, 0.28, 0.28, z0 - 0.1, z0 + h, M["bark"] if rng.random() < 0.6 else M["kerb"], 1.0)
    oriented_box(b, p, yaw, 2.2, 0.14, z0 + h - 0.8, z0 + h - 0.6, M["bark"], 0.9)


def sign_post(b: MeshBuilder, p: np.ndarray, facing: np.ndarray, z0: float, rng: np.random.Generator) -> None:
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


def parked_car(b: MeshBuilder, c: np.ndarray, yaw: float, z0: float, rng: np.random.Generator) -> None:
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


def fence(b: MeshBuilder, a: np.ndarray, e: np.ndarray, z0: float, rng: np.random.Generator,
          picket_spacing: float = 0.0) -> None:
    """A post-and-rail fence from a to e (xy); with picket_spacing > 0 also upright pickets (wood) or bars
    (metal) that far apart, one element repeated along the whole fence."""
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    length = float(np.linalg.norm(e - a))
    yaw = float(np.arctan2(*(e - a)[::-1]))
    wood = rng.random() < 0.5
    mat = M["bark"] if wood else M["metal"]
    for w in np.linspace(0.0, 1.0, max(2, int(length / 2.0) + 1)):
        oriented_box(b, a + w * (e - a), yaw, 0.1, 0.1, z0 - 0.1, z0 + 1.1, mat, 0.9, edges=False)
    mid = 0.5 * (a + e)
    for h in (0.45, 0.95):
        oriented_box(b, mid, yaw, length, 0.05, z0 + h, z0 + h + 0.1, mat, 1.0)
    if picket_spacing > 0.0:
        n = max(1, int(length / picket_spacing))
        at = a + ((np.arange(n) + 0.5) / n)[:, None] * (e - a)
        size = (0.09, 0.025) if wood else (0.03, 0.03)
        prisms(b, at, yaw, size[0], size[1], z0 - 0.05, z0 + (1.0 if wood else 1.05), mat, 1.0 if wood else 0.8)


def hedge(b: MeshBuilder, a: np.ndarray, e: np.ndarray, z0: float, rng: np.random.Generator, leaf_density: float = 0.0,
          leaf_size: float = 0.22) -> None:
    """A hedge from a to e (xy): a closed box (leaf_density 0) or leaves filling that box (m^2 of leaf a m^3)."""
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    yaw = float(np.arctan2(*(e - a)[::-1]))
    length, z1, tint = float(np.linalg.norm(e - a)), z0 + rng.uniform(1.0, 1.8), rng.uniform(0.6, 0.9)
    if leaf_density <= 0.0:
        oriented_box(b, 0.5 * (a + e), yaw, length, 0.9, z0 - 0.1, z1, M["foliage"], tint, edges=False)
        return
    local = _uniform_in_box(rng, np.array([-0.5 * length, -0.45, z0 - 0.1]), np.array([0.5 * length, 0.45, z1]),
                            leaf_density, leaf_size)
    t = (e - a) / length
    xy = 0.5 * (a + e) + local[:, :1] * t + local[:, 1:2] * np.array([-t[1], t[0]])
    leaves(b, np.column_stack([xy, local[:, 2]]), leaf_size, rng, M["leaf"], tint)


def wall(b: MeshBuilder, a: np.ndarray, e: np.ndarray, z0: float, height: float, rng: np.random.Generator,
         plain: int | None = None) -> None:
    """A garden wall or a noise barrier from a to e (xy); plain: a plain material instead of concrete or brick."""
    a, e = np.asarray(a, np.float64)[:2], np.asarray(e, np.float64)[:2]
    yaw = float(np.arctan2(*(e - a)[::-1]))
    mat = M["kerb"] if rng.random() < 0.6 else M["brick"]
    if plain is not None:
        mat = plain
    oriented_box(b, 0.5 * (a + e), yaw, float(np.linalg.norm(e - a)), 0.3, z0 - 0.2, z0 + height, mat,
                 rng.uniform(0.8, 1.1))
