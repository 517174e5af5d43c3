"""The global bundle adjustment's point budget, shared by the adjustment (plvo.loop.global_ba) and by the map,
which may then forget the points no future adjustment would pick (LandmarkMap.drop_unreachable).

Each point belongs to the first keyframe that observes it; a keyframe's points are ranked by views, most first
(ties by id); with more points than the budget, every keyframe keeps its points ranked below one share, the share
the smallest that fills the budget. More keyframes or more views can only lower the share that fills the budget,
so a point ranked above today's share is picked by no later adjustment (as long as the views it is ranked by no
longer change), and forgetting it changes no later share (the points ranked at the share itself are kept: without
them a later share could rise).
"""

from __future__ import annotations

import numpy as np


def owner_ranks(owner: np.ndarray, views: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Points' owner keyframe (P,), views (P,) and ids (P,) -> (P,) rank of each among its owner's points."""
    order = np.lexsort((ids, -np.asarray(views), owner))  # by owner, then most viewed, then id
    owner_sorted = np.asarray(owner)[order]
    rank = np.empty(len(ids), np.int64)
    rank[order] = np.arange(len(ids)) - np.searchsorted(owner_sorted, owner_sorted, side="left")
    return rank


def budget_share(rank: np.ndarray, max_points: int) -> int | None:
    """Ranks (P,) -> the share of each keyframe (points ranked below it are kept), None when all are kept."""
    if max_points <= 0 or len(rank) <= max_points:
        return None
    return max(int(np.sort(rank)[max_points]), 1)  # ranks below it: at most max_points (one a keyframe at least)
