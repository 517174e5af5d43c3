"""How a realistic twin's ground looks: asphalt, verges and pavements that repeat nowhere, lane markings, pavers.

The ideal twins shade the ground with the texture atlas's tiles, which repeat every 2-4 m: a stretch of asphalt or
verge at one distance looks the same 4 m to its side, and ORB, which spreads its keypoints evenly over the image,
puts a third of them on that ground, where their descriptors match several places or none (on twin 04, 63 % of the
candidate matches on asphalt fail the ratio test against 36 % over a real frame). Real streets are smoother at fine
scale, uneven at a scale of metres, and carry strong, trackable marks: dashed lane lines, paving stones, kerbs.
GroundRealism holds each of those settings; GroundShader shades a ground hit from its place (the nearest road
sample's arc length and the offset across the road, twin.layout.Layout.road_coords), so the markings are the same
whichever way the road is driven. Every pattern is box-filtered over the pixel's footprint, so it does not alias
into flicker at a distance.

Marking sizes are those of German roads, where KITTI drove (RMS, Richtlinien fuer die Markierung von Strassen):
lane lines 0.12 m wide, dashed 3 m with 6 m gaps in towns and 6 m with 12 m gaps outside them. IDEAL_GROUND shades
the ground as the twins did before (the atlas's tiles and the edge line), pixel for pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from plvo.errors import SynthError
from plvo_synth.textures import MATERIAL_ID, TextureAtlas
from plvo_synth.twin.layout import ZONES, Layout

M = MATERIAL_ID
TEXTURE_CELL_M = 2.0  # the aperiodic textures' cells (the atlas's tiles repeat every 2-4 m)
WEAR_CELL_TEXELS = 32  # the wear field's cells, in its texels (its tile: WEAR_TILE texels)
OFFSET_RANGE_M = 1000.0  # a cell's seeded offset into its pattern: up to this, far beyond every tile
EDGE_LINE = (0.30, 0.45)  # road edge line: this far inside the road's edge (m), as the ideal twins have it
KERB_M = 0.25
JOINT_GREY = 0.6  # a paving joint's albedo relative to the stone
WEAR_TILE = 256
MIN_OUTER_LANE_M = 1.5  # a lane line is drawn where it leaves at least this much road before the edge line
_PAVED = np.array([z.verge == "pavement" for z in ZONES])


@dataclass(frozen=True)
class GroundRealism:
    """texture_contrast, verge_contrast: the fine texture's contrast on asphalt and on a grass verge, relative to
    the atlas's tile (1: as the tile); aperiodic: break the tiles' repetition (each TEXTURE_CELL_M cell reads the
    tile at its own seeded offset, blended across the cells); wear_contrast, wear_scale_m:
    the uneven shade of real asphalt and verges (patches, stains, fading), 1 sigma and feature size (m);
    lane_width_m: dashed lane lines every lane_width_m across the road, the first lane_width_m / 2 beside the
    driven path, where they leave a lane of at least MIN_OUTER_LANE_M before the edge line (0: none); dash_m,
    gap_m: a dash's and a gap's length per zone (twin.layout.ZONES' order: city, residential, country, highway);
    marking_width_m: the lines' width; paver_m: a paving stone's length and width on city pavements (0: the
    atlas's slabs), paver_contrast: the stones' shade spread (1 sigma), joint_m: the joints' width."""

    texture_contrast: float = 0.15
    verge_contrast: float = 0.3
    aperiodic: bool = True
    wear_contrast: float = 0.2
    wear_scale_m: float = 4.0
    lane_width_m: float = 3.5
    dash_m: tuple[float, float, float, float] = (3.0, 3.0, 6.0, 6.0)
    gap_m: tuple[float, float, float, float] = (6.0, 6.0, 12.0, 12.0)
    marking_width_m: float = 0.12
    paver_m: tuple[float, float] = (0.2, 0.1)
    paver_contrast: float = 0.1
    joint_m: float = 0.01

    @property
    def is_ideal(self) -> bool:
        return self == IDEAL_GROUND

    def check(self) -> None:
        """Raise SynthError naming the first field out of range."""
        for name in ("texture_contrast", "verge_contrast", "wear_contrast", "paver_contrast"):
            _check(name, getattr(self, name), 0.0, 2.0)
        _check("wear_scale_m", self.wear_scale_m, 0.2, 100.0)
        if self.lane_width_m != 0.0:
            _check("lane_width_m", self.lane_width_m, 2.0, 5.0)
        for name in ("dash_m", "gap_m"):
            value = getattr(self, name)
            if len(value) != 4 or not all(0.1 <= x <= 50.0 for x in value):
                raise SynthError(f"scenery.ground.{name} = {value!r}: expected 4 lengths in [0.1, 50] m (city, "
                                 "residential, country, highway)")
        _check("marking_width_m", self.marking_width_m, 0.05, 0.5)
        if len(self.paver_m) != 2 or not (self.paver_m == (0.0, 0.0) or all(0.05 <= x <= 2.0 for x in self.paver_m)):
            raise SynthError(f"scenery.ground.paver_m = {self.paver_m!r}: expected a stone's length and width in "
                             "[0.05, 2] m, or (0, 0)")
        _check("joint_m", self.joint_m, 0.0, 0.05)


def _check(name: str, value: object, lo: float, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise SynthError(f"scenery.ground.{name} = {value!r}: expected a number in [{lo}, {hi}]")


IDEAL_GROUND = GroundRealism(texture_contrast=1.0, verge_contrast=1.0, aperiodic=False, wear_contrast=0.0,
                             lane_width_m=0.0, paver_m=(0.0, 0.0), paver_contrast=0.0)
REALISTIC_GROUND = GroundRealism()


# ---------------------------------------------------------------------------------------------- filtered patterns


def pulse_train(x: np.ndarray, period: np.ndarray | float, width: np.ndarray | float, filter_m: np.ndarray | float
                ) -> np.ndarray:
    """Share of [x - f/2, x + f/2] (f = filter_m) where (x mod period) < width: a dash pattern box-filtered over
    a pixel's footprint (a point sample where f is 0)."""
    x = np.asarray(x, np.float64)
    f = np.asarray(filter_m, np.float64)

    def integral(y: np.ndarray) -> np.ndarray:
        return np.floor(y / period) * width + np.minimum(np.mod(y, period), width)

    point = (np.mod(x, period) < width).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        box = (integral(x + 0.5 * f) - integral(x - 0.5 * f)) / f
    return np.where(f > 1e-6, box, point)


def band(x: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float, filter_m: np.ndarray | float) -> np.ndarray:
    """Share of [x - f/2, x + f/2] inside [lo, hi]: one line across the road, box-filtered."""
    x = np.asarray(x, np.float64)
    f = np.maximum(np.asarray(filter_m, np.float64), 1e-6)
    overlap = np.minimum(x + 0.5 * f, hi) - np.maximum(x - 0.5 * f, lo)
    return np.clip(overlap / np.minimum(f, np.asarray(hi) - np.asarray(lo)), 0.0, 1.0)


def cell_hash(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """(N,) integer cells -> (N,) uniform values in [0, 1), fixed by the seed (a 64-bit integer mix)."""
    with np.errstate(over="ignore"):
        h = (i.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) \
            ^ (j.astype(np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)) ^ np.uint64(seed)
        h ^= h >> np.uint64(31)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(29)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


# ---------------------------------------------------------------------------------------------- shader


class GroundShader:
    """Shades ground hits of a twin by the settings of a GroundRealism (not IDEAL_GROUND: the renderer keeps the
    ideal twins' own code for those)."""

    def __init__(self, settings: GroundRealism, layout: Layout, atlas: TextureAtlas, seed: int) -> None:
        settings.check()
        self.s, self.layout, self.atlas, self.seed = settings, layout, atlas, int(seed)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 81]))
        n = WEAR_TILE
        spec = np.fft.rfft2(rng.standard_normal((n, n)))
        f = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.rfftfreq(n)[None, :]) * n
        spec *= (f >= n / 64) & (f <= n / 8)  # features of 4-32 texels
        wear = np.fft.irfft2(spec, s=(n, n))
        self._wear = ((wear - wear.mean()) / wear.std()).astype(np.float32)
        self._dash = np.array(settings.dash_m)
        self._period = self._dash + np.array(settings.gap_m)

    def _texture(self, mat: int, u: np.ndarray, v: np.ndarray, footprint: np.ndarray, contrast: float) -> np.ndarray:
        """The material's tile at (u, v), its contrast scaled; with `aperiodic` the tile shifted by a seeded
        offset in each TEXTURE_CELL_M cell, blended across cells (see _blended), so it repeats nowhere."""
        mats = np.full(len(u), mat, np.int32)
        if self.s.aperiodic:
            a = self._blended(lambda x, y: self.atlas.sample(mats, x, y, footprint) - 1.0, u, v, TEXTURE_CELL_M, 1)
        else:
            a = self.atlas.sample(mats, u, v, footprint) - 1.0
        return (1.0 + np.float32(contrast) * a).astype(np.float32)

    def _blended(self, lookup: Callable[[np.ndarray, np.ndarray], np.ndarray], x: np.ndarray, y: np.ndarray,
                 cell: float, tag: int) -> np.ndarray:
        """A zero-mean periodic pattern made to repeat nowhere: each cell of a grid of `cell` metres reads it at
        its own seeded offset, and a point blends the four nearest cells' readings with bilinear weights, divided
        by the weights' norm so that the spread stays the pattern's (the cells' readings are uncorrelated)."""
        gx, gy = np.asarray(x, np.float64) / cell - 0.5, np.asarray(y, np.float64) / cell - 0.5
        i0, j0 = np.floor(gx), np.floor(gy)
        fx, fy = gx - i0, gy - j0
        out = np.zeros(len(gx))
        norm = np.zeros(len(gx))
        for di in (0, 1):
            for dj in (0, 1):
                w = (fx if di else 1.0 - fx) * (fy if dj else 1.0 - fy)
                ci, cj = i0 + di, j0 + dj
                ox = cell_hash(ci, cj, self.seed + 2 * tag) * OFFSET_RANGE_M
                oy = cell_hash(ci, cj, self.seed + 2 * tag + 1) * OFFSET_RANGE_M
                out += w * lookup(x + ox, y + oy)
                norm += w * w
        return out / np.sqrt(norm)

    def _wear_at(self, xy: np.ndarray) -> np.ndarray:
        """1 + wear_contrast * a smooth field of feature size about wear_scale_m that repeats nowhere."""
        if self.s.wear_contrast == 0.0:
            return np.ones(len(xy), np.float32)
        texel = self.s.wear_scale_m / 8.0
        field = self._blended(lambda x, y: _bilinear(self._wear, x / texel, y / texel), xy[:, 0], xy[:, 1],
                              WEAR_CELL_TEXELS * texel, 2)
        return (1.0 + self.s.wear_contrast * field).astype(np.float32)

    def markings(self, s_along: np.ndarray, across: np.ndarray, inside: np.ndarray, zone: np.ndarray,
                 on_path: np.ndarray, half_width: np.ndarray, fw_across: np.ndarray | float,
                 fw_along: np.ndarray | float) -> np.ndarray:
        """(N,) share of each pixel covered by a road marking: the edge line and the dashed lane lines."""
        st = self.s
        cover = band(inside, -EDGE_LINE[1], -EDGE_LINE[0], fw_across)
        if st.lane_width_m > 0.0:
            off = np.abs(across)
            w = 0.5 * st.marking_width_m
            dashes = pulse_train(s_along, self._period[zone], self._dash[zone], fw_along)
            # crossing streets carry no lane lines through the junction
            dashes = np.where(on_path | (np.abs(s_along) > 10.0), dashes, 0.0)
            j = 0
            while True:
                o = st.lane_width_m * (j + 0.5)
                room = half_width - EDGE_LINE[1] - o >= MIN_OUTER_LANE_M
                if not np.any(room):
                    break
                line = band(off, o - w, o + w, fw_across) * dashes
                cover = np.maximum(cover, np.where(room, line, 0.0))
                j += 1
        return cover

    def pavers(self, s_along: np.ndarray, across: np.ndarray, fw_across: np.ndarray | float,
               fw_along: np.ndarray | float) -> np.ndarray:
        """(N,) shade of a paved surface: stones in running bond along the road, joints darker."""
        a, b = self.s.paver_m
        row = np.floor(across / b)
        x = s_along + 0.5 * a * np.mod(row, 2.0)
        col = np.floor(x / a)
        stone = 1.0 + self.s.paver_contrast * np.sqrt(12.0) * (cell_hash(col, row, self.seed) - 0.5)
        # the stones' spread averages out once a pixel covers several stones
        fade = np.clip(1.0 - np.maximum(fw_across / b, fw_along / a) / 2.0, 0.0, 1.0)
        stone = 1.0 + (stone - 1.0) * fade
        jw = self.s.joint_m
        joint = 1.0 - (1.0 - pulse_train(across + 0.5 * jw, b, jw, fw_across)) \
            * (1.0 - pulse_train(x + 0.5 * jw, a, jw, fw_along))
        return stone * (1.0 - joint) + JOINT_GREY * joint

    def albedo(self, xy: np.ndarray, d: np.ndarray, k: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray,
               pixel_m: np.ndarray) -> np.ndarray:
        """Camera hits on the ground -> (N,) albedo. d, k: distance to and index of the nearest road sample;
        footprint: the pixel's size along the ground (m, foreshortened), pixel_m: across the line of sight."""
        lay, atlas = self.layout, self.atlas
        hw = lay.half_width[k]
        zone = lay.zone[k].astype(np.int64)
        inside = d - hw
        s_along, across = lay.road_coords(xy, k)
        wear = self._wear_at(xy)
        road = atlas.mat_albedo[M["asphalt"]] * self._texture(M["asphalt"], u, v, footprint,
                                                               self.s.texture_contrast) * wear
        grass = atlas.mat_albedo[M["foliage"]] * self._texture(M["foliage"], u, v, footprint,
                                                                self.s.verge_contrast) * wear
        if self.s.paver_m[0] > 0.0:
            pave = atlas.mat_albedo[M["pavement"]] * self.pavers(s_along, across, pixel_m, footprint) \
                * self._texture(M["kerb"], u, v, footprint, 0.3)
        else:
            pave = atlas.mat_albedo[M["pavement"]] * self._texture(M["pavement"], u, v, footprint, 1.0)
        verge = np.where(_PAVED[zone], pave, grass)
        kerb = atlas.mat_albedo[M["kerb"]] * self._texture(M["kerb"], u, v, footprint, 1.0)
        cover = self.markings(s_along, across, inside, zone, lay.on_path[k], hw, pixel_m, footprint)
        line = atlas.mat_albedo[M["marking"]]
        out = np.where(inside < 0.0, road * (1.0 - cover) + line * cover, verge)
        out = np.where((inside >= 0.0) & (inside < KERB_M), kerb, out)
        return out.astype(np.float32)

    def reflectance(self, xy: np.ndarray, d: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Lidar hits on the ground -> (N,) reflectance: asphalt, paint, kerb, verge (point samples)."""
        lay, atlas = self.layout, self.atlas
        hw = lay.half_width[k]
        zone = lay.zone[k].astype(np.int64)
        inside = d - hw
        s_along, across = lay.road_coords(xy, k)
        cover = self.markings(s_along, across, inside, zone, lay.on_path[k], hw, 0.0, 0.0)
        verge = np.where(_PAVED[zone], atlas.mat_lidar[M["pavement"]], atlas.mat_lidar[M["foliage"]])
        road = atlas.mat_lidar[M["asphalt"]] * (1.0 - cover) + atlas.mat_lidar[M["marking"]] * cover
        out = np.where(inside < 0.0, road, verge)
        out = np.where((inside >= 0.0) & (inside < KERB_M), atlas.mat_lidar[M["kerb"]], out)
        return out.astype(np.float32)


def _bilinear(grid: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A periodic (n,n) grid sampled bilinearly at texel coordinates (x, y)."""
    n = grid.shape[0]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    i0, j0 = x0.astype(np.int64) % n, y0.astype(np.int64) % n
    i1, j1 = (i0 + 1) % n, (j0 + 1) % n
    top = grid[j0, i0] * (1 - fx) + grid[j0, i1] * fx
    bottom = grid[j1, i0] * (1 - fx) + grid[j1, i1] * fx
    return top * (1 - fy) + bottom * fy
