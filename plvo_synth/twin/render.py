"""Camera and lidar of a twin: the town renderer plus movers, cast shadows, a sky, auto exposure and a rolling
lidar sweep.

Light: a sun (direction from the seed, 25-50 deg up) lights every surface that faces it unless a shadow ray from
the hit towards the sun meets the world or a mover; the sky is brighter at the horizon and round the sun, with
clouds. Exposure follows the scene: the gain brings the frame's mean radiance below the horizon to a target.
Ground: one mesh; its shade (asphalt, edge line, pavement or grass) comes from the hit's distance to the nearest
road sample, so the road's edge is smooth whatever the mesh. gt of each frame: z-depth, mover ids, cast-shadow
edges (pixels where a cast shadow begins on a surface continuous in depth and normal: the false edges).
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from plvo.errors import SynthError
from plvo_synth.kitti_calib import CALIB_00_02, KittiCalibration
from plvo_synth.mesh import Town
from plvo_synth.render import AMBIENT, DIFFUSE, MIN_VIEW_COS, NOISE_BANK_EXTRA, Renderer
from plvo_synth.textures import MATERIAL_ID, TextureAtlas
from plvo_synth.twin.camera_effects import IDEAL_CAMERA, CameraRealism, Exposure, develop
from plvo_synth.twin.follow import PoseInterpolator
from plvo_synth.twin.ground import EDGE_LINE, IDEAL_GROUND, GroundRealism, GroundShader
from plvo_synth.twin.layout import ZONES, Layout
from plvo_synth.twin.lidars import LidarEffects, LidarModel
from plvo_synth.twin.traffic import Traffic

M = MATERIAL_ID
SHADOW_EPS_M = 0.03
_VERGE_MAT = {"pavement": M["pavement"], "grass": M["foliage"]}
_ZONE_VERGE = np.array([_VERGE_MAT[z.verge] for z in ZONES], np.int32)


def twin_sun(seed: int) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 61]))
    az, el = rng.uniform(0.0, 2.0 * np.pi), np.radians(rng.uniform(25.0, 50.0))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


class TwinRenderer(Renderer):
    def __init__(self, town: Town, n_ground: int, layout: Layout, traffic: Traffic, lidar: LidarModel,
                 atlas: TextureAtlas, seed: int, calib: KittiCalibration = CALIB_00_02,
                 lidar_effects: LidarEffects | None = None, ground: GroundRealism = IDEAL_GROUND) -> None:
        """calib: the camera's intrinsics and image size; lidar_effects: the lidar's imperfections (None: ideal);
        ground: how the ground looks (twin.ground; IDEAL_GROUND: the ideal twins' tiles and edge line)."""
        super().__init__(town, atlas, seed, calib.K, calib.width, calib.height)
        self._ground_shader = None if ground.is_ideal else GroundShader(ground, layout, atlas, seed)
        self.lidar_effects = lidar_effects
        self.sun = twin_sun(seed)
        self._ndotsun = town.tri_normal.astype(np.float64) @ self.sun
        self.n_ground, self.layout, self.traffic, self.lidar = n_ground, layout, traffic, lidar
        self._lidar_dirs = lidar.rays()
        self._lidar_dt = lidar.ray_times()
        self._columns = lidar.azimuth_steps
        self._beams = len(lidar.elevations_deg)
        crng = np.random.default_rng(np.random.SeedSequence([seed, 62]))
        spec = np.fft.rfft2(crng.standard_normal((256, 256)))
        f = np.hypot(np.fft.fftfreq(256)[:, None], np.fft.rfftfreq(256)[None, :]) * 256
        spec *= (f > 0.5) / np.maximum(f, 1.0) ** 1.6
        clouds = np.fft.irfft2(spec, s=(256, 256))
        self._clouds = ((clouds - clouds.mean()) / clouds.std()).astype(np.float32)

    # ---------------------------------------------------------------- shading pieces

    def _sky_radiance(self, d: np.ndarray) -> np.ndarray:
        """(N,3) world directions -> sky radiance: darker towards the zenith, a glow round the sun, clouds."""
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        up = np.clip(d[:, 2], 0.0, 1.0)
        base = 0.85 - 0.4 * np.sqrt(up)
        glow = 0.25 * np.clip(d @ self.sun, 0.0, 1.0) ** 8
        h = np.maximum(d[:, 2], 0.03)
        cu, cv = d[:, 0] / h * 40.0, d[:, 1] / h * 40.0  # a cloud layer 1 km up, 25 m a texel
        iu = np.floor(cu).astype(np.int64) & 255
        iv = np.floor(cv).astype(np.int64) & 255
        c = np.clip(self._clouds[iv, iu] - 0.3, 0.0, None)
        cloud = np.clip(c * 0.35, 0.0, 0.5) * np.clip(up * 4.0, 0.0, 1.0)
        return (base + glow) * (1.0 - cloud) + cloud * 0.97

    def _ground(self, xy: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray | None, lidar: bool = False,
                pixel_m: np.ndarray | None = None) -> np.ndarray:
        """Ground hits (K,2) -> albedo (or lidar reflectance): road, edge line, verge by distance to the road.
        pixel_m: a camera pixel's size across the line of sight (m), which the realistic ground's markings are
        filtered over (footprint: along the ground, foreshortened)."""
        d, k = self.layout.nearest(xy)
        if self._ground_shader is not None:
            if lidar:
                return self._ground_shader.reflectance(xy, d, k)
            assert footprint is not None  # a camera hit's footprint: only the lidar's hits come without one
            return self._ground_shader.albedo(xy, d, k, u, v, footprint,
                                              footprint if pixel_m is None else pixel_m)
        hw = self.layout.half_width[k]
        zone = self.layout.zone[k]
        inside = d - hw  # < 0 on the road
        verge = _ZONE_VERGE[zone]
        road_mat = np.full(len(d), M["asphalt"], np.int32)
        line = (inside > -EDGE_LINE[1]) & (inside < -EDGE_LINE[0])
        kerb_band = (inside >= 0.0) & (inside < 0.25)
        if lidar:
            a_road, a_verge = self.atlas.mat_lidar[road_mat], self.atlas.mat_lidar[verge]
            line_v, kerb_v = self.atlas.mat_lidar[M["marking"]], self.atlas.mat_lidar[M["kerb"]]
        else:
            assert footprint is not None  # as above
            a_road = self.atlas.mat_albedo[road_mat] * self.atlas.sample(road_mat, u, v, footprint)
            a_verge = self.atlas.mat_albedo[verge] * self.atlas.sample(verge, u, v, footprint)
            line_v = self.atlas.mat_albedo[M["marking"]] * np.ones(len(d), np.float32)
            kerb_v = self.atlas.mat_albedo[M["kerb"]] * self.atlas.sample(np.full(len(d), M["kerb"]), u, v, footprint)
        out = np.where(inside < 0.0, a_road, a_verge)
        out = np.where(line, line_v, out)
        out = np.where(kerb_band, kerb_v, out)
        return out.astype(np.float32)

    def _shadowed(self, points: np.ndarray, time: float) -> np.ndarray:
        """(K,3) surface points -> whether the sun is hidden from them (world or movers)."""
        rays = np.empty((len(points), 6), np.float32)
        rays[:, :3] = points
        rays[:, 3:] = self.sun
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        blocked = np.isfinite(ans["t_hit"].numpy())
        rest = np.flatnonzero(~blocked)
        if len(rest):
            tm = self.traffic.cast(points[rest].astype(np.float64), np.tile(self.sun, (len(rest), 1)), time)[0]
            blocked[rest] = np.isfinite(tm)
        return blocked

    # ---------------------------------------------------------------- camera

    def render_twin(self, T_town_cam: np.ndarray, time: float, rng: np.random.Generator,
                    camera: CameraRealism = IDEAL_CAMERA, poses: PoseInterpolator | None = None, seed: int = 0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """-> image (H,W) uint8, depth (H,W) float32 (inf: sky), mover ids (H,W) uint16, shadow edges (H,W) bool,
        gain (float). camera: what the camera makes of the scene (twin.camera_effects; IDEAL_CAMERA: the old
        images); poses: the camera's path, which motion blur over camera.shutter_s needs; seed: the twin's (the
        rectification's residual warp and the exposure controller's error are fixed per twin)."""
        t, prim, bary, buf = self._cast(self._cam_dirs, T_town_cam)
        origin = T_town_cam[:3, 3].astype(np.float64)
        dirs = buf[:, 3:].astype(np.float64)
        tm, ids, mmat, mtint, mnormal = self.traffic.cast(np.broadcast_to(origin, dirs.shape), dirs, time)
        mover = tm < t
        t = np.where(mover, tm, t)
        ids = np.where(mover, ids, 0).astype(np.uint16)
        n_px = len(t)
        albedo = np.zeros(n_px, np.float32)
        normal = np.zeros((n_px, 3), np.float32)
        hit = np.flatnonzero(np.isfinite(t))
        stat = hit[~mover[hit]]
        pid = prim[stat].astype(np.int64)
        mat, fac, tint, u, v = self._surface(pid, bary[stat])
        side = self._plane_distance(T_town_cam[:3, 3])
        dist = t[stat] * self._cam_norm[stat]
        cos = np.abs(side[pid]) / dist
        footprint = dist / np.float32(self.K[0, 0]) / np.maximum(cos, MIN_VIEW_COS)
        alb, _ = self._albedo(mat, fac, tint, u, v, footprint)
        ground = np.flatnonzero(pid < self.n_ground)
        if len(ground):
            gk = stat[ground]
            xy = origin[:2] + t[gk, None] * dirs[gk, :2]
            alb[ground] = self._ground(xy, u[ground], v[ground], footprint[ground],
                                       pixel_m=dist[ground] / np.float32(self.K[0, 0]))
        albedo[stat] = alb
        normal[stat] = self.town.tri_normal[pid] * np.sign(side[pid])[:, None]
        mv = hit[mover[hit]]
        if len(mv):
            albedo[mv] = self.atlas.mat_albedo[mmat[mv]] * mtint[mv]
            n = mnormal[mv]
            normal[mv] = n * np.where(np.einsum("ij,ij->i", n, dirs[mv]) > 0, -1.0, 1.0)[:, None]
        ndl = normal[hit] @ self.sun.astype(np.float32)
        lit = hit[ndl > 0]
        points = origin + t[lit, None] * dirs[lit] + SHADOW_EPS_M * normal[lit]
        cast_shadow = np.zeros(n_px, bool)
        cast_shadow[lit] = self._shadowed(points, time)
        lambert = np.zeros(n_px, np.float32)
        lambert[hit] = np.maximum(ndl, 0.0)
        lambert[cast_shadow] = 0.0
        radiance = albedo * (AMBIENT + DIFFUSE * lambert)
        sky = np.flatnonzero(~np.isfinite(t))
        radiance[sky] = self._sky_radiance(dirs[sky])
        H, W = self.height, self.width
        depth = t.reshape(H, W).astype(np.float32)
        start = int(rng.integers(0, NOISE_BANK_EXTRA))  # drawn whatever the camera: the lidar's draws stay the same
        T_end = None
        if camera.shutter_s > 0.0:
            if poses is None:
                raise SynthError("render_twin: motion blur (camera.shutter_s > 0) needs the camera's path (poses)")
            T_end = poses(np.array([time + camera.shutter_s]))[0]
        frame = Exposure(self.K, time, seed, depth, T_town_cam, T_end, ids.reshape(H, W) == 0, self._noise, start)
        image, gain = develop(radiance.reshape(H, W), camera, frame,
                              None if camera.noise_model == "bank" else rng.spawn(1)[0])
        edges = shadow_edges(cast_shadow.reshape(H, W), depth, normal.reshape(H, W, 3))
        return image, depth, ids.reshape(H, W), edges, gain

    # ---------------------------------------------------------------- lidar

    def scan_twin(self, poses: PoseInterpolator, frame_time: float, T_cam_velo: np.ndarray,
                  rng: np.random.Generator, effects_rng: np.random.Generator | None = None,
                  compensate: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """One rolling sweep facing forward at frame_time -> (N,4) float32 x, y, z, reflectance and (N,) uint16
        mover ids (0: the static world). Each return is in the sensor frame at its own time, or with `compensate`
        at frame_time (motion-compensated: with lidar effects, by the share of the sweep's motion that KITTI's
        compensation removes, LidarEffects.compensation_gain). effects_rng draws the lidar effects' dropouts and
        crown depths. Returns are column by column (ideal) or, with lidar effects, ring by ring from the top beam as
        KITTI's scans are (each ring in sweep order)."""
        fx = self.lidar_effects
        cast_dirs = self._lidar_dirs if fx is None else fx.cast_dirs
        col_dt = self._lidar_dt[:: self._beams]
        T_cols = poses(frame_time + col_dt) @ T_cam_velo  # (S,4,4) T_town_velo at each column's time
        R = np.repeat(T_cols[:, :3, :3], self._beams, axis=0)
        o = np.repeat(T_cols[:, :3, 3], self._beams, axis=0)
        d = np.einsum("kij,kj->ki", R, cast_dirs.astype(np.float64))
        rays = np.concatenate([o, d], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t, prim, bary = ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), ans["primitive_uvs"].numpy()
        tm, ids, mmat, mtint, mnormal = self.traffic.cast(o, d, frame_time + self._lidar_dt)
        mover = tm < t
        t = np.where(mover, tm, t)
        ids = np.where(mover, ids, 0).astype(np.uint16)
        sigma = self.lidar.range_noise_m if fx is None else fx.range_noise_m
        noise = rng.standard_normal(t.shape, dtype=np.float32) * np.float32(sigma)
        rng_m = t + noise if fx is None else t + noise + fx.ray_range_bias
        keep = np.flatnonzero(np.isfinite(t) & (rng_m > self.lidar.min_range_m) & (rng_m < self.lidar.max_range_m))
        refl = np.zeros(len(t), np.float32)
        stat = keep[~mover[keep]]
        pid = prim[stat].astype(np.int64)
        mat, fac, tint, u, v = self._surface(pid, bary[stat])
        n = self.town.tri_normal[pid]
        cos = np.abs(np.einsum("ij,ij->i", n, d[stat]))
        r = np.take(self.atlas.mat_lidar, mat)
        ground = np.flatnonzero(pid < self.n_ground)
        if len(ground):
            gk = stat[ground]
            xy = o[gk, :2] + t[gk, None] * d[gk, :2]
            r[ground] = self._ground(xy, u[ground], v[ground], None, lidar=True)
        refl[stat] = r * (0.6 + 0.4 * cos)
        mv = keep[mover[keep]]
        if len(mv):
            cosm = np.abs(np.einsum("ij,ij->i", mnormal[mv], d[mv]))
            refl[mv] = self.atlas.mat_lidar[mmat[mv]] * (0.6 + 0.4 * cosm)
        if fx is not None:
            if effects_rng is None:
                raise ValueError("scan_twin: a lidar with effects needs effects_rng")
            keep = self._degrade(fx, keep, stat, mv, mat, tint, ground, mmat, mtint, refl, rng_m, effects_rng)
            # ring by ring from the top beam, as KITTI stores its scans (each ring here in sweep order, clockwise
            # from behind; KITTI's files run each ring counter-clockwise from facing forward)
            keep = keep[np.argsort(keep % self._beams, kind="stable")]
        pts = self._lidar_dirs[keep] * rng_m[keep, None]
        if compensate:
            # each return from the sensor at its own time into the sensor at frame_time (KITTI's odometry scans),
            # with the motion the compensation knows: over whole GPS/INS record periods, a gain on the sweep's times
            T_ref = poses(np.array([frame_time]))[0] @ T_cam_velo
            gain = 1.0 if fx is None else fx.compensation_gain(frame_time)
            T_known = T_cols if gain == 1.0 else poses(frame_time + gain * col_dt) @ T_cam_velo
            rel = np.linalg.inv(T_ref)[None] @ T_known  # (S,4,4) T_ref_col as compensated
            col = keep // self._beams
            p = pts.astype(np.float64)
            pts = np.einsum("kij,kj->ki", rel[col, :3, :3], p) + rel[col, :3, 3]
        kept = np.round(np.clip(refl[keep], 0.0, 0.99), 2)
        return np.concatenate([pts, kept[:, None]], axis=1).astype(np.float32), ids[keep]

    def _degrade(self, fx: LidarEffects, keep: np.ndarray, stat: np.ndarray, mv: np.ndarray, mat: np.ndarray,
                 tint: np.ndarray, ground: np.ndarray, mmat: np.ndarray, mtint: np.ndarray, refl: np.ndarray,
                 rng_m: np.ndarray, effects_rng: np.random.Generator) -> np.ndarray:
        """The returns that a real sensor would lose dropped from `keep`; returns from tree crowns pushed into
        them (rng_m changed in place)."""
        material = np.full(len(refl), -1, np.int32)
        darkness = refl.copy()
        material[stat] = mat
        material[stat[ground]] = -1  # the ground's verge shares foliage's material id but is a surface
        darkness[stat] *= tint
        if len(mv):
            material[mv] = mmat[mv]
            darkness[mv] *= mtint[mv]
        rng_m[keep] += fx.crown_depth(material[keep], effects_rng)
        return keep[~fx.missed(keep, darkness[keep], material[keep], effects_rng)]


def shadow_edges(shadow: np.ndarray, depth: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Pixels where a cast shadow starts or ends between neighbours on one smooth surface (depth within 3 %,
    normals within 10 deg): edges that only the light makes. Dilated by one pixel (LSD's segments lie on them)."""
    out = np.zeros(shadow.shape, bool)
    for dy, dx in ((0, 1), (1, 0)):
        a = (slice(0, shadow.shape[0] - dy), slice(0, shadow.shape[1] - dx))
        b = (slice(dy, None), slice(dx, None))
        change = shadow[a] != shadow[b]
        za, zb = depth[a], depth[b]
        with np.errstate(invalid="ignore"):  # inf - inf where both see the sky
            smooth = np.isfinite(za) & np.isfinite(zb) & (np.abs(za - zb) < 0.03 * np.minimum(za, zb) + 0.02)
        same = np.einsum("ijk,ijk->ij", normal[a], normal[b]) > 0.985
        e = change & smooth & same
        out[a] |= e
        out[b] |= e
    return cv2.dilate(out.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
