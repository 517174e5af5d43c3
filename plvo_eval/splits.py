"""Which sequences the defaults may be tuned on, and which are held out.

A default chosen by looking at a sequence's figure says nothing about the next sequence; the figures that say how
plvo does on data it was not tuned on are the held-out ones. The development set is what every default of
plvo.config was chosen on (docs/results/defaults.md): the generated towns 20-22, the 51 real frames of KITTI 04 in
../shared/data, and four of the eleven KITTI twins, picked for what they hold (03: slow, turning streets; 04: a
straight 394 m road, where a heading error shows alone; 08: streets revisited the other way round, on which the
lidar place recognition's thresholds were read; 09: a return to its start after 1.7 km). The other seven twins are
held out: no default changes for their sake. The evaluation report pools each group apart.
"""

from __future__ import annotations

DEVELOPMENT_TWINS = ("03", "04", "08", "09")
HELD_OUT_TWINS = ("00", "01", "02", "05", "06", "07", "10")
DEVELOPMENT_TOWNS = ("20", "21", "22")

DEVELOPMENT, HELD_OUT = "development", "held-out"


def twin_split(label: str) -> str | None:
    """A report row's label ("twin04", as plvo eval run --twins names them) -> DEVELOPMENT, HELD_OUT, or None when it
    is not one of the eleven twins."""
    if not label.startswith("twin"):
        return None
    seq = label[len("twin"):]
    if seq in DEVELOPMENT_TWINS:
        return DEVELOPMENT
    return HELD_OUT if seq in HELD_OUT_TWINS else None
