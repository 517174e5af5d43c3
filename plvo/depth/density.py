"""Patch sizes that follow the scan's ring spacing, so that sparser lidars (16, 32 beams) still give depth priors.

The paper's patches (7 px around a point, 4 px around a line) suit an HDL-64E seen by KITTI's camera, whose rings
fall about 5 px apart in the image. A 16-beam scan puts them about 20 px apart: a 15x15 patch then holds returns of
one ring at most, a line of points, and no plane can be fitted. The ring spacing is measured on the projected
scan itself (the median vertical gap between returns in narrow image columns) and the patches are scaled by its
ratio to the HDL-64E's when it is clearly larger; a dense scan keeps the configured sizes exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from plvo.config import DepthConfig
from plvo.depth.projection import ProjectedScan

_COLUMN_PX = 4  # wider than the HDL-64E's azimuth step in KITTI's image (about 2.2 px), so each ring has a return
_MIN_GAP_PX = 1.5  # smaller gaps are neighbours on one ring, not the next ring
_MIN_GAPS = 100  # fewer measured gaps: too little of the scan in view to tell


def ring_spacing_px(proj: ProjectedScan) -> float | None:
    """Median vertical gap (px) between successive rings in the image, or None when too few returns are in view."""
    if len(proj) < 2:
        return None
    col = np.floor(proj.uv[:, 0] / _COLUMN_PX).astype(np.int64)
    v = proj.uv[:, 1]
    # by column, then v: one float key (v < span) sorts ten times faster than lexsort; v itself gives the gaps
    v0 = v.min()
    span = float(np.ceil(v.max() - v0)) + 1.0
    order = np.argsort(col * span + (v - v0))
    col, v = col[order], v[order]
    gaps = np.diff(v)[col[1:] == col[:-1]]
    gaps = gaps[gaps > _MIN_GAP_PX]
    return float(np.median(gaps)) if len(gaps) >= _MIN_GAPS else None


def adapt_patches(cfg: DepthConfig, proj: ProjectedScan) -> tuple[DepthConfig, float]:
    """(cfg with point and line patches scaled to the scan's ring spacing, the scale); cfg itself (scale 1) when
    adaptation is off, the spacing unknown or within cfg.adapt_min_ratio of the HDL-64E's."""
    if not cfg.adapt_to_ring_spacing:
        return cfg, 1.0
    spacing = ring_spacing_px(proj)
    if spacing is None:
        return cfg, 1.0
    ratio = spacing / cfg.reference_ring_spacing_px
    if ratio < cfg.adapt_min_ratio:
        return cfg, 1.0
    ratio = min(ratio, cfg.adapt_max_ratio)
    return replace(cfg, point_patch_px=int(round(cfg.point_patch_px * ratio)),
                   line_patch_px=int(round(cfg.line_patch_px * ratio))), ratio
