"""How hard a twin's scenery is: leafy crowns and hedges, plain walls, rows of identical houses, railings.

Real streets are hard for a camera and a lidar in ways that closed blobs and textured boxes are not: a tree's crown
is thousands of small leaves at many depths (the camera sees them self-occluding and shifting with parallax, the
lidar gets returns scattered through the crown and some rays pass through it); many walls are plain; a row of
houses shares one window pattern and a fence repeats one picket, so descriptors match the wrong copy. The foliage
(crown, hedge and shrub densities, the shrubs' chances) is calibrated against KITTI 04 frames 0-50 and raw drive
2011_09_26_drive_0009 frames 0-50 on the lidar's foliage signature and the camera's FAST corner count
(scripts/scenery_stats.py; the figures in docs/twins.md); the shares of plain walls, rows and railings are set by
judgement (they move those statistics little). IDEAL_SCENERY builds the world the twins had before, triangle for
triangle.

Leaf density is a leaf area density (m^2 of leaf per m^3 of crown, as forestry measures it: broadleaf crowns hold
about 0.5-2.5): with leaves facing every way a ray is stopped at a rate of half of it a metre (Beer-Lambert with
G = 0.5), so a crown 4 m across lets through exp(-2 * density) of the rays that cross its middle.
"""

from __future__ import annotations

from dataclasses import dataclass

from plvo.errors import SynthError
from plvo_synth.twin.ground import IDEAL_GROUND, REALISTIC_GROUND, GroundRealism


@dataclass(frozen=True)
class SceneryRealism:
    """What makes the scenery hard. A density of 0 keeps the closed shape (a crown blob, a hedge box)."""

    crown_leaf_density: float = 1.0  # m^2 of leaf per m^3 in the lobes of a tree's crown (0: a closed blob)
    hedge_leaf_density: float = 5.0  # the same in a hedge (0: a box)
    leaf_size_m: float = 0.22  # edge of a leaf triangle: a cluster of leaves, ~8 px across at 20 m
    plain_wall_share: float = 0.4  # buildings, garden walls and noise barriers whose walls are plain
    facade_row_share: float = 0.5  # share of ROW_M squares whose houses are one design (one window pattern)
    row_m: float = 36.0  # side of a square of the building lattice whose houses may share a design
    railing_share: float = 0.5  # fences of pickets or railing bars rather than two rails
    picket_spacing_m: float = 0.16
    # chance that a cell of the shrub lattice (SHRUB_SPACING_M) grows a bush, per zone in layout.ZONES' order:
    # city, residential, country, highway (verges, gardens, field edges, embankments)
    shrub_p: tuple[float, float, float, float] = (0.4, 0.4, 0.7, 0.6)
    shrub_leaf_density: float = 3.0
    ground: GroundRealism = REALISTIC_GROUND  # how the ground looks (twin.ground)

    def check(self) -> None:
        """Raise SynthError naming the first field out of range."""
        for name in ("crown_leaf_density", "hedge_leaf_density", "shrub_leaf_density"):
            value = getattr(self, name)
            if not 0.0 <= value <= 20.0:
                raise SynthError(f"scenery.{name} = {value!r}: expected m^2 of leaf per m^3 in [0, 20]")
        for name in ("plain_wall_share", "facade_row_share", "railing_share"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise SynthError(f"scenery.{name} = {value!r}: expected a share in [0, 1]")
        if len(self.shrub_p) != 4 or not all(0.0 <= p <= 1.0 for p in self.shrub_p):
            raise SynthError(f"scenery.shrub_p = {self.shrub_p!r}: expected 4 chances in [0, 1] (city, residential, "
                             "country, highway)")
        if not 0.05 <= self.leaf_size_m <= 1.0:
            raise SynthError(f"scenery.leaf_size_m = {self.leaf_size_m!r}: expected 0.05-1 m")
        if not 0.05 <= self.picket_spacing_m <= 1.0:
            raise SynthError(f"scenery.picket_spacing_m = {self.picket_spacing_m!r}: expected 0.05-1 m")
        if not 9.0 <= self.row_m <= 500.0:
            raise SynthError(f"scenery.row_m = {self.row_m!r}: expected 9-500 m (at least one building cell)")
        if not isinstance(self.ground, GroundRealism):
            raise SynthError(f"scenery.ground: expected a twin.ground.GroundRealism, got {self.ground!r}")
        self.ground.check()


IDEAL_SCENERY = SceneryRealism(crown_leaf_density=0.0, hedge_leaf_density=0.0, plain_wall_share=0.0,
                               facade_row_share=0.0, railing_share=0.0, shrub_p=(0.0, 0.0, 0.0, 0.0),
                               ground=IDEAL_GROUND)
REALISTIC_SCENERY = SceneryRealism()
