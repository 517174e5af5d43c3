"""Moving cars of a twin: ahead in the car's lane, oncoming in the other lane, crossing on the crossing streets.

Each mover is a function of time (s, frame i at i * 0.1 s) -> body pose T_town_body (x forward, y left, z up, origin
on the ground under the box centre), so the camera (at the frame's time) and the lidar (at each return's own time
in the sweep) see it where it is at that instant. Ray casts run in each mover's body frame against its shape.
A car ahead keeps at least its own gap in front of the ego car; a mover that would come too close to the ego car
(COLLIDE_M) at a frame is dropped (deterministically), so nothing drives through the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from plvo_synth.mesh import MeshBuilder
from plvo_synth.sensors import FRAME_DT
from plvo_synth.textures import MATERIAL_ID
from plvo_synth.twin import shapes
from plvo_synth.twin.layout import CROSS_HALF_M, Layout

M = MATERIAL_ID
LANE_M = 3.5  # the oncoming lane's centre, left of the driven path
COLLIDE_M = 3.0  # least gap (m) between the ego car's box and a mover's centre in the same lane
KINDS = ("ahead", "oncoming", "crossing")


@dataclass(frozen=True)
class Shape:
    name: str
    size: tuple[float, float, float]  # length, width, height of its box (m)
    vertices: np.ndarray
    triangles: np.ndarray
    material: np.ndarray
    tint: np.ndarray
    normal: np.ndarray


def _shape(name: str, length: float, width: float, body_h: float, cabin: bool, tint: float) -> Shape:
    b = MeshBuilder()
    if cabin:
        shapes.oriented_box(b, (0.0, 0.0), 0.0, length - 0.2, width - 0.04, 0.3, body_h, M["car_paint"], tint)
        shapes.oriented_box(b, (-0.2, 0.0), 0.0, 0.55 * length, width - 0.24, body_h, body_h + 0.45, M["car_glass"],
                            1.0, top=M["car_paint"])
        height = body_h + 0.45
    else:
        shapes.oriented_box(b, (0.0, 0.0), 0.0, length - 0.2, width - 0.04, 0.3, body_h, M["car_paint"], tint)
        shapes.oriented_box(b, (0.5 * length - 0.35, 0.0), 0.0, 0.3, width - 0.1, 1.0, body_h - 0.2,
                            M["car_glass"], 1.0)
        height = body_h
    for sa in (-0.33 * length, 0.33 * length):
        for sb in (-0.5 * width + 0.12, 0.5 * width - 0.12):
            shapes.oriented_box(b, (sa, sb), 0.0, 0.64, 0.24, 0.0, 0.62, M["tyre"], 1.0, edges=False)
    town = b.build()
    return Shape(name, (length, width, height), town.vertices, town.triangles, town.tri_material, town.tri_tint,
                 town.tri_normal)


SHAPES = (
    _shape("car_dark", 4.4, 1.84, 1.0, True, 0.25),
    _shape("car_light", 4.4, 1.84, 1.0, True, 1.6),
    _shape("car_mid", 4.2, 1.78, 1.0, True, 0.8),
    _shape("van", 4.9, 1.96, 2.0, False, 1.3),
)


@dataclass(frozen=True)
class Mover:
    id: int  # 1-based: the value in the masks and lidar labels
    kind: str
    shape: int
    speed: float  # m/s
    t0: float  # ahead: when it is at s0; oncoming: when it meets the ego car; crossing: when it is at the crossing
    s0: float = 0.0
    gap: float = 0.0  # ahead: least distance kept in front of the ego car
    crossing: int = -1
    sign: float = 1.0  # crossing: which way along the crossing street


class Traffic:
    """The movers of a twin and their poses at any time; casts rays against them."""

    def __init__(self, layout: Layout, road: np.ndarray, first: int, n_frames: int, n_movers: int, seed: int) -> None:
        """road (K,3): the driven road in order, beyond the frames at both ends; frames first..first+n_frames-1
        of it are the ego car's."""
        self.layout = layout
        seg = np.linalg.norm(np.diff(road[:, :2], axis=0), axis=1)
        self.S = np.concatenate([[0.0], np.cumsum(seg)])  # arc length (xy) along the road
        self.times = np.arange(n_frames) * FRAME_DT
        self.ego_S = self.S[first:first + n_frames]
        self.ego_xy = road[first:first + n_frames, :2]
        self.road = road
        self.scenes = []
        for s in SHAPES:
            scene = o3d.t.geometry.RaycastingScene()
            # open3d's stubs have no Tensor(ndarray) overload; the call is open3d's documented one
            scene.add_triangles(o3d.core.Tensor(s.vertices), o3d.core.Tensor(s.triangles))  # type: ignore[call-overload]
            self.scenes.append(scene)
        self.movers = self._draw(n_movers, seed)

    # ---------------------------------------------------------------- the movers

    def _draw(self, n: int, seed: int) -> list[Mover]:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 60]))
        T = float(self.times[-1])
        out: list[Mover] = []
        crossings = self.layout.crossings
        n_ahead = 0
        for _ in range(n):
            kind = KINDS[int(rng.choice(3, p=[0.3, 0.45, 0.25]))]
            if kind == "crossing" and not len(crossings):
                kind = "oncoming"
            shape = int(rng.integers(len(SHAPES)))
            t0 = float(rng.uniform(0.0, T))
            ego_v = max(float(np.interp(t0 + 1.0, self.times, self.ego_S)
                              - np.interp(t0 - 1.0, self.times, self.ego_S)) / 2.0, 4.0)
            if kind == "ahead":
                n_ahead += 1
                m = Mover(0, kind, shape, float(np.clip(ego_v * rng.uniform(0.6, 1.1), 3.0, 30.0)), t0,
                          float(np.interp(t0, self.times, self.ego_S) + rng.uniform(15.0, 45.0)),
                          gap=10.0 + 9.0 * n_ahead)
            elif kind == "oncoming":
                m = Mover(0, kind, shape, float(np.clip(ego_v * rng.uniform(0.7, 1.3), 4.0, 30.0)), t0,
                          float(np.interp(t0, self.times, self.ego_S)))
            else:
                c = int(rng.integers(len(crossings)))
                cxy = crossings[c, :2]
                d = np.linalg.norm(self.ego_xy - cxy, axis=1)
                t_ego = float(self.times[int(np.argmin(d))])
                side = 1.0 if rng.random() < 0.5 else -1.0
                m = Mover(0, kind, shape, float(rng.uniform(6.0, 12.0)), t_ego + side * float(rng.uniform(2.5, 6.0)),
                          crossing=c, sign=1.0 if rng.random() < 0.5 else -1.0)
            out.append(m)
        kept = [m for m in out if not self._collides(m)]
        fields = ("kind", "shape", "speed", "t0", "s0", "gap", "crossing", "sign")
        return [Mover(i + 1, *(getattr(m, f) for f in fields)) for i, m in enumerate(kept)]

    def _collides(self, m: Mover) -> bool:
        """Would the mover's centre come within the ego car's box grown by COLLIDE_M along and 2.6 m across?"""
        T, alive = self.pose(m, self.times)
        _, fwd = self._along(self.ego_S, 0.0, False)
        f = fwd[:, :2] / np.maximum(np.linalg.norm(fwd[:, :2], axis=1, keepdims=True), 1e-9)
        rel = T[:, :2, 3] - self.ego_xy
        along = np.abs(np.einsum("ij,ij->i", rel, f))
        across = np.abs(rel[:, 0] * f[:, 1] - rel[:, 1] * f[:, 0])
        return bool((alive & (along < 2.5 + COLLIDE_M) & (across < 2.6)).any())

    # ---------------------------------------------------------------- poses

    def _along(self, s: np.ndarray, lateral: float, reverse: bool) -> tuple[np.ndarray, np.ndarray]:
        """Arc lengths on the driven path -> positions (K,3) offset `lateral` to the left, headings (K,3) unit."""
        xy = np.column_stack([np.interp(s, self.S, self.road[:, 0]), np.interp(s, self.S, self.road[:, 1])])
        z = np.interp(s, self.S, self.road[:, 2])
        ahead = np.column_stack([np.interp(s + 1.0, self.S, self.road[:, 0]),
                                 np.interp(s + 1.0, self.S, self.road[:, 1])])
        behind = np.column_stack([np.interp(s - 1.0, self.S, self.road[:, 0]),
                                  np.interp(s - 1.0, self.S, self.road[:, 1])])
        dz = np.interp(s + 1.0, self.S, self.road[:, 2]) - np.interp(s - 1.0, self.S, self.road[:, 2])
        t = ahead - behind
        norm = np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
        t3 = np.column_stack([t, dz])
        fwd = t3 / np.maximum(np.linalg.norm(t3, axis=1, keepdims=True), 1e-9)
        left = np.column_stack([-t[:, 1], t[:, 0]]) / norm
        pos = np.column_stack([xy + lateral * left, z])
        return pos, (-fwd if reverse else fwd)

    def pose(self, m: Mover, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Times (K,) -> (K,4,4) T_town_body and (K,) whether the mover exists then."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        end = float(self.S[-1])
        if m.kind == "ahead":
            s = np.maximum(np.interp(t, self.times, self.ego_S) + m.gap, m.s0 + m.speed * (t - m.t0))
            pos, fwd = self._along(s, 0.0, False)
            alive = s <= end
        elif m.kind == "oncoming":
            s = m.s0 - m.speed * (t - m.t0)
            pos, fwd = self._along(s, LANE_M, True)
            alive = (s >= 0.0) & (s <= end)
        else:
            c = self.layout.crossings[m.crossing]
            d = m.sign * c[3:5]
            u = m.speed * (t - m.t0)
            right = np.array([d[1], -d[0]])
            xy = c[:2] + u[:, None] * d + 1.75 * right
            pos = np.column_stack([xy, np.full(len(t), c[2])])
            fwd = np.tile([d[0], d[1], 0.0], (len(t), 1))
            alive = np.abs(u) < CROSS_HALF_M - 5.0
        up = np.array([0.0, 0.0, 1.0])
        left = np.cross(up, fwd)
        left /= np.maximum(np.linalg.norm(left, axis=1, keepdims=True), 1e-9)
        top = np.cross(fwd, left)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = fwd, left, top, pos
        return T, alive

    def size(self, m: Mover) -> tuple[float, float, float]:
        return SHAPES[m.shape].size

    # ---------------------------------------------------------------- ray casts

    def cast(self, origins: np.ndarray, dirs: np.ndarray, times: np.ndarray | float, max_range: float = 150.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rays (N,3) origins and directions (town frame; t counts in units of |dir|) at times (N,) ->
        t_hit (N,) (inf: no mover), mover id (N,) (0: none), material (N,), tint (N,), normal (N,3) town frame."""
        n = len(dirs)
        t_best = np.full(n, np.inf, np.float32)
        ids = np.zeros(n, np.uint16)
        mat = np.zeros(n, np.int32)
        tint = np.ones(n, np.float32)
        normal = np.zeros((n, 3), np.float32)
        if not self.movers or n == 0:
            return t_best, ids, mat, tint, normal
        if np.ndim(times) == 0:  # one instant (a camera frame): no per-ray lookup of poses
            uniq, inv = np.array([float(times)]), np.zeros(n, np.int64)
        else:
            uniq, inv = np.unique(np.asarray(times, np.float64), return_inverse=True)
            inv = inv.ravel()
        unit = dirs / np.sqrt(np.einsum("ij,ij->i", dirs, dirs))[:, None]
        one_origin = origins.strides[0] == 0  # a camera's rays, from np.broadcast_to: no reduction over n rows
        o_lo, o_hi = (origins[0], origins[0]) if one_origin else (origins.min(axis=0), origins.max(axis=0))
        # A mover's bounding sphere (centre C, radius r) is near a ray o + s u when |C - o|^2 - ((C - o).u)^2 < r^2.
        # At one instant C is one point, so the per-ray terms are expanded once here and each mover costs a matrix-
        # vector product (the camera: one origin, so one product over the directions; shadow rays: one per mover).
        if len(uniq) == 1:
            o_dot_u = unit @ o_lo if one_origin else np.einsum("ij,ij->i", origins, unit)
            o_dot_o = float(o_lo @ o_lo) if one_origin else np.einsum("ij,ij->i", origins, origins)
        for m in self.movers:
            T, alive = self.pose(m, uniq)
            L, W, H = self.size(m)
            radius = 0.5 * float(np.sqrt(L * L + W * W + H * H)) + 0.2
            far = np.maximum(np.maximum(o_lo - T[:, :3, 3], T[:, :3, 3] - o_hi), 0.0)
            alive = alive & (np.linalg.norm(far, axis=1) < max_range + radius)
            if not alive.any():
                continue
            centre = T[:, :3, 3] + 0.5 * H * T[:, :3, 2]
            if len(uniq) == 1:
                C = centre[0]
                b = unit @ C - o_dot_u
                c_dot_c = C @ C - 2.0 * (o_lo @ C if one_origin else origins @ C) + o_dot_o
                near = (b > -radius) & (c_dot_c - b * b < radius * radius)
            else:
                c = centre[inv] - origins
                b = np.einsum("ij,ij->i", c, unit)
                near = alive[inv] & (b > -radius) & (np.einsum("ij,ij->i", c, c) - b * b < radius * radius)
            k = np.flatnonzero(near)
            if not len(k):
                continue
            Tk = T[inv[k]]
            R = Tk[:, :3, :3]
            o_body = np.einsum("kji,kj->ki", R, origins[k] - Tk[:, :3, 3])
            d_body = np.einsum("kji,kj->ki", R, dirs[k])
            rays = np.concatenate([o_body, d_body], axis=1).astype(np.float32)
            ans = self.scenes[m.shape].cast_rays(o3d.core.Tensor.from_numpy(rays))
            th = ans["t_hit"].numpy()
            better = th < t_best[k]
            if not better.any():
                continue
            kb = k[better]
            prim = ans["primitive_ids"].numpy()[better].astype(np.int64)
            shape = SHAPES[m.shape]
            t_best[kb] = th[better]
            ids[kb] = m.id
            mat[kb] = shape.material[prim]
            tint[kb] = shape.tint[prim]
            normal[kb] = np.einsum("kij,kj->ki", R[better], shape.normal[prim])
        return t_best, ids, mat, tint, normal

    def describe(self) -> list[dict]:
        return [{"id": m.id, "kind": m.kind, "shape": SHAPES[m.shape].name, "size_lwh_m": list(SHAPES[m.shape].size),
                 "speed_mps": m.speed} for m in self.movers]
