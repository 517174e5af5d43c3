"""Procedural surface textures: periodic tiles (brick, plaster, asphalt, ...) with mip levels, and the materials.

Every material samples one tile at a fixed texel density (texels per metre) in the surface's own metric (u, v)
coordinates. All tiles and levels live in one flat float32 array, so a lookup for any mix of materials is a single
numpy gather; the mip level follows the pixel footprint so that distant surfaces do not alias into noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TILE = 256  # texels a side of a repeating tile (sign plates use SIGN_TILE)
SIGN_TILE = 64


@dataclass(frozen=True)
class Material:
    name: str
    tile: str
    texels_per_m: float
    albedo: float  # mean grey albedo in [0, 1]
    lidar_reflectance: float  # KITTI-like reflectance in [0, 1] at normal incidence


MATERIALS: tuple[Material, ...] = (
    Material("asphalt", "asphalt", 64.0, 0.30, 0.28),
    Material("marking", "paint", 64.0, 0.85, 0.75),
    Material("pavement", "pavement", 128.0, 0.55, 0.32),
    Material("kerb", "concrete", 128.0, 0.68, 0.35),
    Material("brick", "brick", 125.0, 0.45, 0.30),
    Material("plaster", "plaster", 64.0, 0.70, 0.35),
    Material("roof", "concrete", 64.0, 0.35, 0.20),
    Material("ledge", "concrete", 128.0, 0.80, 0.35),
    Material("metal", "paint", 128.0, 0.40, 0.45),
    Material("car_paint", "paint", 64.0, 0.50, 0.40),
    Material("car_glass", "glass", 64.0, 0.12, 0.05),
    Material("tyre", "asphalt", 128.0, 0.08, 0.05),
    Material("bark", "bark", 256.0, 0.30, 0.25),
    Material("foliage", "foliage", 96.0, 0.35, 0.40),
    Material("sign_circle", "sign_circle", SIGN_TILE / 0.7, 0.70, 0.95),
    Material("sign_triangle", "sign_triangle", SIGN_TILE / 0.7, 0.70, 0.95),
    Material("sign_text", "sign_text", SIGN_TILE / 0.7, 0.60, 0.95),
    Material("door", "plaster", 64.0, 0.18, 0.20),
    # The twins' realistic scenery (plvo_synth.twin.scenery_realism) only; appended, so that the town's
    # material ids and tiles stay as they were.
    Material("leaf", "foliage", 96.0, 0.30, 0.40),  # a leaf triangle shows one or two blotches of the tile
    Material("plain_wall", "paint", 32.0, 0.72, 0.35),  # rendered, painted walls: faint shading only
    Material("barrier", "paint", 32.0, 0.50, 0.30),  # plain concrete or metal noise-barrier panels
)
MATERIAL_ID = {m.name: i for i, m in enumerate(MATERIALS)}
SIGN_MATERIALS = ("sign_circle", "sign_triangle", "sign_text")


def _band_noise(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """(n,n) periodic noise with spatial frequencies between lo and hi cycles per tile, zero mean, unit std."""
    spec = np.fft.rfft2(rng.standard_normal((n, n)))
    fy = np.fft.fftfreq(n)[:, None] * n
    fx = np.fft.rfftfreq(n)[None, :] * n
    f = np.hypot(fx, fy)
    spec *= (f >= lo) & (f <= hi)
    out = np.fft.irfft2(spec, s=(n, n))
    return (out - out.mean()) / max(out.std(), 1e-9)


def _brick(rng: np.random.Generator) -> np.ndarray:
    n, bw, bh = TILE, 32, 8
    row = np.arange(n)[:, None] // bh
    col = (np.arange(n)[None, :] + (row % 2) * (bw // 2)) // bw
    shade = rng.normal(1.0, 0.12, (n // bh, n // bw + 1))
    tex = shade[row, col % (n // bw)] * (1.0 + 0.06 * _band_noise(rng, n, 8, 100))
    mortar = (np.arange(n)[:, None] % bh == 0) | ((np.arange(n)[None, :] + (row % 2) * (bw // 2)) % bw == 0)
    return np.where(mortar, 1.45, tex)


def _plaster(rng: np.random.Generator) -> np.ndarray:
    tex = 1.0 + 0.06 * _band_noise(rng, TILE, 1, 6) + 0.09 * _band_noise(rng, TILE, 6, 40)
    spots = _band_noise(rng, TILE, 20, 60) > 2.6  # grime dots give ORB corners on plain walls
    return np.where(spots, 0.7, tex)


def _asphalt(rng: np.random.Generator) -> np.ndarray:
    tex = 1.0 + 0.10 * _band_noise(rng, TILE, 1, 5) + 0.18 * _band_noise(rng, TILE, 20, 128)
    patches = _band_noise(rng, TILE, 2, 8) > 1.8
    cracks = np.abs(_band_noise(rng, TILE, 3, 10)) < 0.03
    return np.where(cracks, 0.55, np.where(patches, tex * 0.8, tex))


def _pavement(rng: np.random.Generator) -> np.ndarray:
    n, s = TILE, 64
    i, j = np.arange(n)[:, None] // s, np.arange(n)[None, :] // s
    shade = rng.normal(1.0, 0.08, (n // s, n // s))[i, j]
    gaps = (np.arange(n)[:, None] % s < 2) | (np.arange(n)[None, :] % s < 2)
    return np.where(gaps, 0.6, shade * (1.0 + 0.06 * _band_noise(rng, n, 10, 100)))


def _concrete(rng: np.random.Generator) -> np.ndarray:
    return 1.0 + 0.05 * _band_noise(rng, TILE, 1, 8) + 0.10 * _band_noise(rng, TILE, 20, 128)


def _paint(rng: np.random.Generator) -> np.ndarray:
    return 1.0 + 0.03 * _band_noise(rng, TILE, 1, 16)


def _glass(rng: np.random.Generator) -> np.ndarray:
    return 1.0 + 0.25 * _band_noise(rng, TILE, 1, 3)


def _bark(rng: np.random.Generator) -> np.ndarray:
    streaks = np.repeat(_band_noise(rng, TILE, 8, 40)[:1], TILE, axis=0)
    return 1.0 + 0.25 * streaks + 0.1 * _band_noise(rng, TILE, 10, 60)


def _foliage(rng: np.random.Generator) -> np.ndarray:
    blobs = _band_noise(rng, TILE, 6, 24)
    return np.clip(1.0 + 0.45 * blobs + 0.15 * _band_noise(rng, TILE, 30, 90), 0.2, 2.0)


def _sign(kind: str, rng: np.random.Generator) -> np.ndarray:
    n = SIGN_TILE
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n - 0.5
    tex = np.full((n, n), 1.2)
    if kind == "sign_circle":
        r = np.hypot(x, y)
        tex[(r > 0.36) & (r < 0.46)] = 0.35  # red ring shows dark in grey
        tex[r >= 0.46] = 0.9
        tex[(np.abs(x) < 0.2) & (np.abs(y) < 0.15) & ((np.abs(x) % 0.1) < 0.05)] = 0.1  # digits
    elif kind == "sign_triangle":
        inside = (y > -0.4) & (y < 0.4) & (np.abs(x) < (y + 0.4) * 0.55)
        inner = (y > -0.25) & (y < 0.3) & (np.abs(x) < (y + 0.25) * 0.45)
        tex[inside] = 0.35
        tex[inner] = 1.2
        tex[(np.abs(x) < 0.04) & (y > -0.05) & (y < 0.2)] = 0.1
        tex[~inside] = 0.9
    else:
        tex[:] = 0.45  # blue board with white text blocks
        cells = rng.random((8, 8)) > 0.45
        cy, cx = ((y + 0.5) * 8).astype(int), ((x + 0.5) * 8).astype(int)
        tex[cells[cy, cx] & (np.abs(y) < 0.35) & (np.abs(x) < 0.42) & ((cy % 2) == 1)] = 1.4
    return tex


_TILE_MAKERS = {
    "brick": _brick, "plaster": _plaster, "asphalt": _asphalt, "pavement": _pavement, "concrete": _concrete,
    "paint": _paint, "glass": _glass, "bark": _bark, "foliage": _foliage,
}


@dataclass(frozen=True)
class TextureAtlas:
    """All tiles and their mip levels in one flat array.

    texels: (N,) float32 multipliers around 1; offset, size: (n_tiles, n_levels) int32 (size 1 past the last
    level); mat_tile: (n_materials,) tile index; mat_density: texels per metre; mat_albedo, mat_lidar: (n_mat,).
    """

    texels: np.ndarray
    offset: np.ndarray
    size: np.ndarray
    n_levels: np.ndarray
    mat_tile: np.ndarray
    mat_density: np.ndarray
    mat_albedo: np.ndarray
    mat_lidar: np.ndarray

    def sample(self, mat: np.ndarray, u: np.ndarray, v: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """(N,) materials, surface coordinates u, v (m), pixel footprint (m) -> (N,) float32 texture value."""
        tile = np.take(self.mat_tile, mat)
        dens = np.take(self.mat_density, mat)
        level = np.rint(np.log2(np.maximum(footprint_m * dens, 1.0))).astype(np.int32)
        np.minimum(level, np.take(self.n_levels, tile) - 1, out=level)
        flat = tile * self.size.shape[1] + level
        mask = np.take(self.size.ravel(), flat) - 1  # tile sizes are powers of two: wrap with a bit mask
        scale = dens / np.left_shift(1, level).astype(np.float32)
        iu = np.floor(u * scale).astype(np.int32) & mask
        iv = np.floor(v * scale).astype(np.int32) & mask
        return np.take(self.texels, np.take(self.offset.ravel(), flat) + iv * (mask + 1) + iu)


def build_atlas(seed: int) -> TextureAtlas:
    """Generate every tile from `seed` and lay out its mip pyramid."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7_001]))
    names = sorted({m.tile for m in MATERIALS})
    tiles = {}
    for name in names:
        tiles[name] = _sign(name, rng) if name.startswith("sign") else _TILE_MAKERS[name](rng)
    max_levels = int(np.log2(TILE)) + 1
    offset = np.zeros((len(names), max_levels), np.int32)
    size = np.ones((len(names), max_levels), np.int32)
    n_levels = np.zeros(len(names), np.int32)
    chunks, pos = [], 0
    for t, name in enumerate(names):
        img = tiles[name].astype(np.float64)
        level = 0
        while True:
            offset[t, level], size[t, level] = pos, img.shape[0]
            chunks.append(img.ravel())
            pos += img.size
            level += 1
            if img.shape[0] == 1:
                break
            img = img.reshape(img.shape[0] // 2, 2, img.shape[1] // 2, 2).mean(axis=(1, 3))
        n_levels[t] = level
    index = {name: i for i, name in enumerate(names)}
    return TextureAtlas(
        texels=np.concatenate(chunks).astype(np.float32),
        offset=offset,
        size=size,
        n_levels=n_levels,
        mat_tile=np.array([index[m.tile] for m in MATERIALS], np.int32),
        mat_density=np.array([m.texels_per_m for m in MATERIALS], np.float32),
        mat_albedo=np.array([m.albedo for m in MATERIALS], np.float32),
        mat_lidar=np.array([m.lidar_reflectance for m in MATERIALS], np.float32),
    )
