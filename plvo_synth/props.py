"""Street furniture and road paint: lamp posts, sign posts, trees, parked cars, lane markings, zebra crossings.

Positions come from the caller (town.py); each helper adds its triangles and straight edges to a MeshBuilder.
A street is described by a point on its centre line and a unit direction; `n` below is a unit normal pointing
from the street towards the side being furnished.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from plvo_synth.mesh import EDGE_TEXTURE, MeshBuilder
from plvo_synth.textures import MATERIAL_ID, SIGN_MATERIALS

M = MATERIAL_ID
MARK_Z = 0.01  # road paint floats 1 cm above the asphalt so the ray caster sees it first
KERB_H = 0.15


def _box_at(b: MeshBuilder, centre_xy: npt.ArrayLike, half_xy: npt.ArrayLike, z0: float, z1: float, material: int,
            tint: float = 1.0, top: int | None = None) -> None:
    c, h = np.asarray(centre_xy, float), np.abs(np.asarray(half_xy, float))
    b.add_box([c[0] - h[0], c[1] - h[1], z0], [c[0] + h[0], c[1] + h[1], z1], material, tint, top_material=top)


def lamp_post(b: MeshBuilder, p: np.ndarray, n: np.ndarray, rng: np.random.Generator) -> None:
    """A lamp post at p (on the pavement) with its arm reaching over the road (towards -n)."""
    h = rng.uniform(6.0, 8.0)
    _box_at(b, p, (0.09, 0.09), KERB_H, h, M["metal"], rng.uniform(0.6, 1.2))
    arm_c = np.asarray(p) - 0.8 * np.asarray(n)
    half = np.abs(np.asarray(n)) * 0.8 + (1 - np.abs(np.asarray(n))) * 0.05
    _box_at(b, arm_c, half, h - 0.1, h, M["metal"], 0.8)
    head = np.asarray(p) - 1.5 * np.asarray(n)
    _box_at(b, head, np.abs(np.asarray(n)) * 0.3 + (1 - np.abs(np.asarray(n))) * 0.15, h - 0.3, h - 0.1,
            M["metal"], 1.8)


def sign_post(b: MeshBuilder, p: np.ndarray, d: np.ndarray, rng: np.random.Generator) -> None:
    """A sign post at p whose plate faces traffic coming along -d (the plate's front looks along -d)."""
    d = np.asarray(d, float)
    side = np.array([-d[1], d[0]])
    _box_at(b, p, (0.04, 0.04), KERB_H, 2.6, M["metal"], 0.9)
    size = 0.7
    c = np.asarray(p) - 0.06 * d
    half = np.abs(side) * size / 2 + np.abs(d) * 0.02
    _box_at(b, c, half, 2.3, 2.3 + size, M["metal"], 0.7)
    front = c - 0.021 * d
    corner = np.array([*(front - side * size / 2), 2.3])
    mat = M[SIGN_MATERIALS[int(rng.integers(len(SIGN_MATERIALS)))]]
    b.add_quad(corner, [*(side * size), 0.0], [0.0, 0.0, size], mat, 1.0)


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    # One subdivision: 80 faces, round enough for a crown.
    verts, cache, faces = list(v), {}, []

    def mid(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in cache:
            verts.append((verts[i] + verts[j]) / 2)
            cache[key] = len(verts) - 1
        return cache[key]

    for a, c, e in f:
        ab, bc, ca = mid(a, c), mid(c, e), mid(e, a)
        faces += [[a, ab, ca], [c, bc, ab], [e, ca, bc], [ab, bc, ca]]
    v = np.array(verts)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.array(faces)


_SPHERE = _icosphere()


def tree(b: MeshBuilder, p: np.ndarray, rng: np.random.Generator) -> None:
    """A tree at p: a square trunk and a lumpy crown."""
    trunk_h = rng.uniform(2.2, 3.2)
    _box_at(b, p, (0.15, 0.15), KERB_H, trunk_h + 0.5, M["bark"], rng.uniform(0.7, 1.2))
    r, zs = rng.uniform(1.4, 2.3), rng.uniform(0.9, 1.3)
    verts, faces = _SPHERE
    lumps = verts * r * rng.uniform(0.85, 1.15, (len(verts), 1)) * np.array([1.0, 1.0, zs])
    centre = np.array([p[0], p[1], trunk_h + 0.9 * r * zs])
    b.add_blob(lumps + centre, faces, M["foliage"], rng.uniform(0.7, 1.2), centre)


def parked_car(b: MeshBuilder, c: np.ndarray, d: np.ndarray, rng: np.random.Generator) -> None:
    """A parked car (boxes) centred at c, its length along d."""
    d = np.abs(np.asarray(d, float))
    side = 1.0 - d
    tint = float(rng.choice([0.25, 0.5, 0.9, 1.3, 1.7]))
    _box_at(b, c, d * 2.1 + side * 0.9, 0.3, 1.0, M["car_paint"], tint)
    cab_c = np.asarray(c) - d * rng.uniform(0.0, 0.3)
    _box_at(b, cab_c, d * 1.15 + side * 0.8, 1.0, 1.45, M["car_glass"], 1.0, top=M["car_paint"])
    for sa in (-1.4, 1.4):
        for sb in (-0.8, 0.8):
            _box_at(b, np.asarray(c) + d * sa + side * sb, d * 0.32 + side * 0.12, 0.0, 0.62, M["tyre"], 1.0)


def _paint_rect(b: MeshBuilder, centre: np.ndarray, d: np.ndarray, length: float, width: float) -> None:
    """Road paint: a length x width rectangle centred at `centre`, its length along unit d."""
    d = np.asarray(d, float)
    side = np.array([-d[1], d[0]])
    c0 = np.asarray(centre, float) - d * length / 2 - side * width / 2
    corner = np.array([c0[0], c0[1], MARK_Z])
    eu, ev = np.array([*(d * length), 0.0]), np.array([*(side * width), 0.0])
    b.add_quad(corner, eu, ev, M["marking"], 1.0, origin=[0.0, 0.0, MARK_Z])
    pts = [corner, corner + eu, corner + eu + ev, corner + ev]
    for k in range(4):
        b.add_edge(pts[k], pts[(k + 1) % 4], EDGE_TEXTURE)


def street_paint(b: MeshBuilder, a: npt.ArrayLike, e: npt.ArrayLike, road_half: float,
                 rng: np.random.Generator) -> None:
    """Markings of one street leg from crossing a to crossing e (centre line points): dashes, stop lines, zebras."""
    a, e = np.asarray(a, float), np.asarray(e, float)
    length = float(np.linalg.norm(e - a))
    d = (e - a) / length
    s = road_half + 6.0
    while s + 3.0 < length - road_half - 6.0:
        _paint_rect(b, a + d * (s + 1.5), d, 3.0, 0.15)
        s += 9.0
    for end, out in ((a, d), (e, -d)):  # `out` points from the crossing into this leg
        lane = np.array([out[1], -out[0]])  # the right lane of traffic driving towards this crossing is on -lane
        _paint_rect(b, end + out * (road_half + 5.5) - lane * road_half / 2, lane, road_half - 0.3, 0.4)
        if rng.random() < 0.4:
            for k in np.arange(-road_half + 0.7, road_half - 0.4, 1.2):
                _paint_rect(b, end + out * (road_half + 3.0) + lane * k, out, 3.0, 0.5)
