"""Camera images and Velodyne scans of the town with open3d's CPU ray caster.

One `cast_rays` call per image and one per scan, over ray directions precomputed in the sensor frame; everything
after the cast (texture coordinates, mip-mapped texture lookup, facade layouts, Lambert shading, noise) is
vectorised numpy over the hits.
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from plvo_synth import sensors
from plvo_synth.facade import shade_facade
from plvo_synth.mesh import Town
from plvo_synth.textures import TextureAtlas

AMBIENT, DIFFUSE = 0.3, 0.85
SKY_RADIANCE = 0.95
EXPOSURE = 1.15  # radiance 1 maps to 255 * EXPOSURE before the gain
OPTICS_BLUR_SIGMA_PX = 0.6
READ_NOISE_GREY = 1.5  # grey levels, 1 sigma
MIN_VIEW_COS = 0.25
NOISE_BANK_EXTRA = 1 << 16  # footprint growth on slanted surfaces is capped at 1 / MIN_VIEW_COS


def sun_direction(seed: int) -> np.ndarray:
    """(3,) unit vector towards the sun in the town frame, elevation 35-60 deg, azimuth from the seed."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 6]))
    az, el = rng.uniform(0.0, 2.0 * np.pi), np.radians(rng.uniform(35.0, 60.0))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


class Renderer:
    """Renders cam0 images and HDL-64E scans of one Town (town frame: x east, y north, z up)."""

    def __init__(self, town: Town, atlas: TextureAtlas, seed: int, K: np.ndarray = sensors.K_CAM0,
                 width: int = sensors.IMAGE_WIDTH, height: int = sensors.IMAGE_HEIGHT) -> None:
        self.town, self.atlas = town, atlas
        self.K, self.width, self.height = K, width, height
        self.sun = sun_direction(seed)
        self.scene = o3d.t.geometry.RaycastingScene()
        # open3d's stubs have no Tensor(ndarray) overload; the call is open3d's documented one
        self.scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles))  # type: ignore[call-overload]
        self._cam_dirs = sensors.camera_rays(K, width, height)
        self._cam_norm = np.linalg.norm(self._cam_dirs, axis=1)
        self._lidar_dirs = sensors.lidar_rays()
        self._sky = SKY_RADIANCE - 0.15 * np.clip(-self._cam_dirs[:, 1] / self._cam_norm, 0.0, 1.0)
        # Per-triangle table gathered once per hit: tint, then u and v at vertex A and their steps to B and C
        # (texture coordinates are affine over a triangle, so the caster's barycentrics give them exactly).
        tri = town.vertices[town.triangles.astype(np.int64)].astype(np.float64)  # (T,3,3)
        rel = tri - town.tri_origin[:, None, :]
        uu = np.einsum("tkj,tj->tk", rel, town.tri_u)
        vv = np.einsum("tkj,tj->tk", rel, town.tri_v)
        # One contiguous array per column: 1-D gathers beat a row gather followed by strided arithmetic.
        self._tri_cols = [np.ascontiguousarray(c, np.float32) for c in (
            town.tri_tint, uu[:, 0], uu[:, 1] - uu[:, 0], uu[:, 2] - uu[:, 0],
            vv[:, 0], vv[:, 1] - vv[:, 0], vv[:, 2] - vv[:, 0])]
        self._tri_mat = town.tri_material.astype(np.int32)
        self._tri_fac = town.tri_facade.astype(np.int32)
        self._tri_a = tri[:, 0]
        self._ndotsun = town.tri_normal.astype(np.float64) @ self.sun
        self._facades_t = np.ascontiguousarray(town.facades.T, np.float32)  # (N_PARAMS,F): columns gather
        # Read noise: slices of one long seeded sequence at a per-frame random offset (fresh draws cost 10 ms).
        bank_rng = np.random.default_rng(np.random.SeedSequence([seed, 10]))
        self._noise = bank_rng.standard_normal(width * height + NOISE_BANK_EXTRA, dtype=np.float32)
        self._noise *= np.float32(READ_NOISE_GREY)

    def _cast(self, dirs: np.ndarray, T_town_sensor: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One cast_rays call -> hit distance (in units of |dir|), triangle ids, barycentrics, (N,6) rays."""
        buf = np.empty((len(dirs), 6), np.float32)
        buf[:, :3] = T_town_sensor[:3, 3]
        R = T_town_sensor[:3, :3].astype(np.float32)
        for k in range(3):  # column by column: far faster than an (N,3) @ (3,3) matmul into a strided view
            buf[:, 3 + k] = dirs[:, 0] * R[k, 0] + dirs[:, 1] * R[k, 1] + dirs[:, 2] * R[k, 2]
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(buf))
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), ans["primitive_uvs"].numpy(), buf

    def _surface(self, pid: np.ndarray, bary: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Hits -> material, facade row (-1: none), tint, texture coordinates u, v (m)."""
        tint, u0, du1, du2, v0, dv1, dv2 = (np.take(c, pid) for c in self._tri_cols)
        b1, b2 = np.ascontiguousarray(bary[:, 0]), np.ascontiguousarray(bary[:, 1])
        return np.take(self._tri_mat, pid), np.take(self._tri_fac, pid), tint, u0 + b1 * du1 + b2 * du2, \
            v0 + b1 * dv1 + b2 * dv2

    def _plane_distance(self, origin: np.ndarray) -> np.ndarray:
        """(T,) signed distance of the sensor from each triangle's plane (the side it sees)."""
        return np.einsum("tj,tj->t", self.town.tri_normal, (origin[None, :] - self._tri_a).astype(np.float32))

    def _albedo(self, mat: np.ndarray, fac: np.ndarray, tint: np.ndarray, u: np.ndarray, v: np.ndarray,
                footprint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) albedo and facade override (NaN where the wall's own material shows)."""
        tex = self.atlas.sample(mat, u, v, footprint)
        albedo = self.atlas.mat_albedo[mat] * tint * tex
        override = np.full(len(mat), np.nan, np.float32)
        on_wall = np.flatnonzero(fac >= 0)
        if len(on_wall):
            override[on_wall] = shade_facade(np.take(self._facades_t, fac[on_wall], axis=1), u[on_wall], v[on_wall])
        painted = np.flatnonzero(np.isfinite(override))
        albedo[painted] = override[painted] * (0.85 + 0.15 * tex[painted])
        return albedo, override

    def render(self, T_town_cam: np.ndarray, gain: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(4,4) camera pose -> (H,W) uint8 image and (H,W) float32 z-depth (m, inf where the sky shows)."""
        t, prim, bary, _ = self._cast(self._cam_dirs, T_town_cam)
        hit = np.flatnonzero(np.isfinite(t))
        pid = prim[hit].astype(np.int64)
        mat, fac, tint, u, v = self._surface(pid, bary[hit])
        side = self._plane_distance(T_town_cam[:3, 3])
        dist = t[hit] * self._cam_norm[hit]
        cos = np.abs(side[pid]) / dist
        lambert = np.maximum(np.sign(side) * self._ndotsun, 0.0).astype(np.float32)[pid]
        footprint = dist / np.float32(self.K[0, 0]) / np.maximum(cos, MIN_VIEW_COS)
        albedo, _ = self._albedo(mat, fac, tint, u, v, footprint)
        radiance = self._sky.copy()
        radiance[hit] = albedo * (AMBIENT + DIFFUSE * lambert)
        img = radiance.reshape(self.height, self.width) * np.float32(255.0 * EXPOSURE * gain)
        img = cv2.GaussianBlur(img, (0, 0), OPTICS_BLUR_SIGMA_PX)
        start = int(rng.integers(0, NOISE_BANK_EXTRA))
        img += self._noise[start:start + img.size].reshape(img.shape)
        image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return image, t.reshape(self.height, self.width)

    def scan(self, T_town_velo: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(4,4) lidar pose -> (N,4) float32 x, y, z, reflectance in the Velodyne frame, one return per ray."""
        t, prim, bary, _ = self._cast(self._lidar_dirs, T_town_velo)
        rng_m = t + rng.standard_normal(t.shape, dtype=np.float32) * np.float32(sensors.LIDAR_RANGE_NOISE_M)
        hit = np.flatnonzero(np.isfinite(t) & (rng_m > sensors.LIDAR_MIN_RANGE_M)
                             & (rng_m < sensors.LIDAR_MAX_RANGE_M))
        pid = prim[hit].astype(np.int64)
        mat, fac, _, u, v = self._surface(pid, bary[hit])
        cos = np.abs(self._plane_distance(T_town_velo[:3, 3])[pid]) / t[hit]
        refl = np.take(self.atlas.mat_lidar, mat) * (0.6 + 0.4 * cos)  # KITTI's road reads ~0.2-0.3 at grazing
        on_wall = np.flatnonzero(fac >= 0)
        painted = shade_facade(np.take(self._facades_t, fac[on_wall], axis=1), u[on_wall], v[on_wall])
        refl[on_wall[painted < 0.35]] *= 0.3  # glass and doors return weakly (NaN compares false)
        pts = self._lidar_dirs[hit] * rng_m[hit, None]
        refl = np.round(np.clip(refl, 0.0, 0.99), 2)  # KITTI stores reflectance in steps of 0.01
        return np.concatenate([pts, refl[:, None]], axis=1).astype(np.float32)
