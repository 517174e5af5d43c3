"""The town's triangle mesh with per-triangle surface data, and a builder for quads, boxes and blobs.

Each triangle carries a material, a brightness tint, an optional facade row and a planar (u, v) frame in metres
(origin + two unit axes), so the renderer turns any ray hit into texture coordinates with a few gathers.
Straight edges (box edges, window outlines, markings) are collected alongside as ground truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from plvo_synth.facade import N_PARAMS, facade_rectangles

EDGE_GEOMETRIC = 0  # a crease or silhouette of the geometry (box edges, kerbs, poles)
EDGE_TEXTURE = 1  # a painted line on a flat surface (window and door outlines, signs, road markings)
_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Town:
    """The scene in the town frame (x east, y north, z up, metres).

    vertices: (V,3) float32; triangles: (T,3) uint32; tri_material: (T,) int64; tri_tint: (T,) float32;
    tri_facade: (T,) int64 row of `facades` or -1; tri_origin, tri_u, tri_v, tri_normal: (T,3) float32;
    facades: (F,N_PARAMS); edges: (E,2,3) float64 straight edge segments; edge_kind: (E,) int8 (EDGE_*).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    tri_material: np.ndarray
    tri_tint: np.ndarray
    tri_facade: np.ndarray
    tri_origin: np.ndarray
    tri_u: np.ndarray
    tri_v: np.ndarray
    tri_normal: np.ndarray
    facades: np.ndarray
    edges: np.ndarray
    edge_kind: np.ndarray


class MeshBuilder:
    """Accumulates triangles with surface data and edges; `build()` returns a Town."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._frames: list[np.ndarray] = []  # per triangle: origin, u axis, v axis (T_k,9)
        self._scalars: list[np.ndarray] = []  # rows (n_tris, material, tint, facade)
        self._facades: list[np.ndarray] = []
        self._edges: list[np.ndarray] = []
        self._edge_kind: list[np.ndarray] = []
        self._n_verts = 0
        self._boxes: list[tuple] = []

    def add_edges(self, edges: np.ndarray, kind: int = EDGE_GEOMETRIC) -> None:
        """(E,2,3) segments in the town frame."""
        edges = np.asarray(edges, np.float64).reshape(-1, 2, 3)
        self._edges.append(edges)
        self._edge_kind.append(np.full(len(edges), kind, np.int8))

    def add_edge(self, a: npt.ArrayLike, b: npt.ArrayLike, kind: int = EDGE_GEOMETRIC) -> None:
        self.add_edges(np.array([a, b], np.float64), kind)

    def add_facade(self, row: np.ndarray) -> int:
        self._facades.append(np.asarray(row, np.float64))
        return len(self._facades) - 1

    def add_quad(self, corner: npt.ArrayLike, eu: npt.ArrayLike, ev: npt.ArrayLike, material: int, tint: float = 1.0,
                 facade: int = -1, origin: npt.ArrayLike | None = None) -> None:
        """Quad corner, corner+eu, corner+eu+ev, corner+ev; texture u along eu, v along ev from `origin`."""
        corner, eu, ev = (np.asarray(x, np.float64) for x in (corner, eu, ev))
        verts = np.array([corner, corner + eu, corner + eu + ev, corner + ev])
        au, av = eu / np.sqrt(eu @ eu), ev / np.sqrt(ev @ ev)
        o = corner if origin is None else np.asarray(origin, np.float64)
        frame = np.concatenate([o, au, av])
        self._push(verts, _QUAD_TRIS, np.stack([frame, frame]), material, tint, facade)

    def add_box(self, lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray, material: int,
                tint: float = 1.0, facades: Sequence[int] | None = None, top_material: int | None = None,
                edges: bool = True) -> None:
        """Axis-aligned box without a bottom; walls -y, +x, +y, -x get facades[i] (row index or -1), u along the
        wall from its left foot seen from outside. Boxes are meshed together, vectorised, in build()."""
        fac = (-1, -1, -1, -1) if facades is None else tuple(facades)
        top = material if top_material is None else top_material
        self._boxes.append((*lo, *hi, material, top, tint, *fac, float(edges)))

    def add_blob(self, verts: np.ndarray, tris: np.ndarray, material: int, tint: float,
                 origin: npt.ArrayLike) -> None:
        """Closed mesh with per-triangle texture frames (u horizontal, v up the slope)."""
        verts, tris = np.asarray(verts, np.float64), np.asarray(tris)
        p = verts[tris]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        au = np.cross(_UP, n)
        au_len = np.linalg.norm(au, axis=1, keepdims=True)
        au = np.where(au_len > 1e-6, au / np.maximum(au_len, 1e-12), [1.0, 0.0, 0.0])
        av = np.cross(n, au)
        o = np.broadcast_to(np.asarray(origin, np.float64), au.shape)
        self._push(verts, tris, np.concatenate([o, au, av], axis=1), material, tint, -1)

    def add_triangles(self, verts: np.ndarray, tris: np.ndarray, frames: np.ndarray, material: int,
                      tint: float = 1.0, facade: int = -1) -> None:
        """(V,3) vertices, (T,3) triangles, (T,9) texture frames (origin, u axis, v axis) of one material."""
        self._push(np.asarray(verts, np.float64), np.asarray(tris), np.asarray(frames, np.float64), material, tint,
                   facade)

    def add_facade_edges(self, corner: npt.ArrayLike, along: npt.ArrayLike, fac: int) -> None:
        """The window, door and sign outlines of facade row `fac` on a wall from `corner` along `along`."""
        self._facade_edges(np.asarray(corner, np.float64), np.asarray(along, np.float64), fac)

    def _push(self, verts: np.ndarray, tris: np.ndarray, frames: np.ndarray, material: int, tint: float,
              facade: int) -> None:
        self._verts.append(verts)
        self._tris.append(tris + self._n_verts)
        self._n_verts += len(verts)
        self._frames.append(frames)
        self._scalars.append(np.array([[len(tris), material, tint, facade]], np.float64))

    def _facade_edges(self, corner: np.ndarray, along: np.ndarray, fac: int) -> None:
        rects = facade_rectangles(self._facades[fac])
        if not len(rects):
            return
        au = along / np.linalg.norm(along)
        u0, v0, u1, v1 = rects.T
        corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        pts = np.stack([corner + u[:, None] * au + v[:, None] * _UP for u, v in corners], axis=1)  # (R,4,3)
        self.add_edges(np.stack([pts, np.roll(pts, -1, axis=1)], axis=2).reshape(-1, 2, 3), EDGE_TEXTURE)

    def _mesh_boxes(self) -> None:
        if not self._boxes:
            return
        b = np.array(self._boxes, np.float64)
        lo, hi = b[:, 0:3], b[:, 3:6]
        d = hi - lo
        zero = np.zeros(len(b))
        ex, ey, ez = (np.stack([d[:, 0], zero, zero], 1), np.stack([zero, d[:, 1], zero], 1),
                      np.stack([zero, zero, d[:, 2]], 1))
        corners = [lo, np.stack([hi[:, 0], lo[:, 1], lo[:, 2]], 1), np.stack([hi[:, 0], hi[:, 1], lo[:, 2]], 1),
                   np.stack([lo[:, 0], hi[:, 1], lo[:, 2]], 1), np.stack([lo[:, 0], lo[:, 1], hi[:, 2]], 1)]
        eus, evs = [ex, ey, -ex, -ey, ex], [ez, ez, ez, ez, ey]
        top_origin = np.stack([zero, zero, hi[:, 2]], 1)
        for k in range(5):  # four walls, then the roof
            c, eu, ev = corners[k], eus[k], evs[k]
            verts = np.stack([c, c + eu, c + eu + ev, c + ev], axis=1).reshape(-1, 3)
            tris = (np.arange(len(b))[:, None, None] * 4 + _QUAD_TRIS[None]).reshape(-1, 3)
            au = eu / np.linalg.norm(eu, axis=1, keepdims=True)
            av = ev / np.linalg.norm(ev, axis=1, keepdims=True)
            frames = np.repeat(np.concatenate([c if k < 4 else top_origin, au, av], axis=1), 2, axis=0)
            self._verts.append(verts)
            self._tris.append(tris + self._n_verts)
            self._n_verts += len(verts)
            self._frames.append(frames)
            mat = b[:, 6] if k < 4 else b[:, 7]
            fac = b[:, 9 + k] if k < 4 else np.full(len(b), -1.0)
            self._scalars.append(np.stack([np.full(len(b), 2.0), mat, b[:, 8], fac], axis=1))
            if k < 4:
                for i in np.flatnonzero(fac >= 0):
                    self._facade_edges(c[i], eu[i], int(fac[i]))
        with_edges = b[:, 13] > 0
        self.add_edges(_box_edges(lo[with_edges], hi[with_edges]))
        self._boxes = []

    def build(self) -> Town:
        self._mesh_boxes()
        sc = np.concatenate(self._scalars)
        counts = sc[:, 0].astype(np.int64)
        frames = np.concatenate(self._frames)
        au, av = frames[:, 3:6], frames[:, 6:9]
        normal = np.cross(au, av)
        return Town(
            vertices=np.concatenate(self._verts).astype(np.float32),
            triangles=np.concatenate(self._tris).astype(np.uint32),
            tri_material=np.repeat(sc[:, 1].astype(np.int64), counts),
            tri_tint=np.repeat(sc[:, 2].astype(np.float32), counts),
            tri_facade=np.repeat(sc[:, 3].astype(np.int64), counts),
            tri_origin=frames[:, :3].astype(np.float32),
            tri_u=au.astype(np.float32),
            tri_v=av.astype(np.float32),
            tri_normal=(normal / np.linalg.norm(normal, axis=1, keepdims=True)).astype(np.float32),
            facades=np.array(self._facades, np.float64).reshape(-1, N_PARAMS),
            edges=np.concatenate(self._edges) if self._edges else np.zeros((0, 2, 3)),
            edge_kind=np.concatenate(self._edge_kind) if self._edge_kind else np.zeros(0, np.int8),
        )


_QUAD_TRIS = np.array([[0, 1, 2], [0, 2, 3]])


def _box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(B,3) corners -> (12*B,2,3) edges of axis-aligned boxes."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    c = np.stack([np.stack([x, y, z], 1) for x in (lo[:, 0], hi[:, 0]) for y in (lo[:, 1], hi[:, 1])
                  for z in (lo[:, 2], hi[:, 2])], axis=1)  # (B,8,3)
    pairs = np.array([(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)])
    return c[:, pairs].reshape(-1, 2, 3)
