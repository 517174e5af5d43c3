"""Keyframe database for loop detection (paper II-F): inverted index over point and line words, combined score,
DBoW2-style candidate selection (normalised scores, islands, temporal consistency).

Combined score. The paper prints s = exp((1 - s_p)^2) exp((1 - s_l)^2), which *grows* as the keyframes become less
similar (it is 1 for identical keyframes and e^2 for unrelated ones). Its intent is a Gaussian of the distance
(1 - s_p, 1 - s_l) of the pair from perfect similarity, both cues multiplied; the sign of the exponent was lost.
We use that Gaussian, rescaled to [0, 1] so that unrelated keyframes score 0 (which the DBoW2 normalisation
s / s(K, K_prev) needs: a floor of e^-2 would squash every ratio towards 1):

    s = (exp(-[(1 - s_p)^2 + (1 - s_l)^2]) - e^-2) / (1 - e^-2)

It rises with both similarities, is 1 for identical keyframes and 0 when they share no word. For the small BoW
scores typical of real revisits (0.05-0.3) it behaves like 0.31 (s_p + s_l), i.e. the two cues add; near
s_p, s_l -> 1 it rewards keyframes on which both agree. When a keyframe has no lines (points-only ablation, or a
scene without lines), s_l is taken equal to s_p so that the missing cue neither helps nor penalises.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from plvo.config import LoopConfig
from plvo.loop.vocabulary import BowVector, l1_score

log = logging.getLogger(__name__)

_E2 = float(np.exp(-2.0))


def combine_scores(s_p: np.ndarray | float, s_l: np.ndarray | float) -> np.ndarray:
    """Point and line L1 scores (any shape, in [0,1]) -> combined score of the same shape in [0,1]."""
    d = (1.0 - np.asarray(s_p, float)) ** 2 + (1.0 - np.asarray(s_l, float)) ** 2
    return (np.exp(-d) - _E2) / (1.0 - _E2)


class _InvertedIndex:
    """Inverted index of one vocabulary as a few blocks of (word, keyframe slot, weight) entries sorted by word.

    Blocks hold 1, 2, 4, ... keyframes like the digits of a binary counter: adding a keyframe appends a block
    and merges the last two while they hold equally many keyframes (a stable radix sort of int32 words), so an
    entry is re-sorted O(log K) times and a query searches O(log K) blocks. In each block a query finds its
    words' runs by binary search and gathers them in one go.
    """

    def __init__(self) -> None:
        self._blocks: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []  # (n_kf, word, slot, weight)

    def add(self, slot: int, bow: BowVector) -> None:
        self._blocks.append((1, bow.words, np.full(len(bow), slot, np.int32), bow.weights))
        while len(self._blocks) >= 2 and self._blocks[-1][0] == self._blocks[-2][0]:
            a, b = self._blocks.pop(), self._blocks.pop()
            word = np.concatenate([b[1], a[1]])
            order = np.argsort(word, kind="stable")
            self._blocks.append((a[0] + b[0], word[order], np.concatenate([b[2], a[2]])[order],
                                 np.concatenate([b[3], a[3]])[order]))

    def nbytes(self) -> int:
        return sum(sum(a.nbytes for a in block[1:]) for block in self._blocks)

    def scores(self, bow: BowVector, n_slots: int) -> np.ndarray:
        """L1 score of the query against every slot, (n_slots,) float (sum over shared words of min weights)."""
        out = np.zeros(n_slots)
        for _, word, slot, weight in self._blocks:
            lo = np.searchsorted(word, bow.words, side="left")
            cnt = np.searchsorted(word, bow.words, side="right") - lo
            total = int(cnt.sum())
            if total == 0:
                continue
            idx = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)
            contrib = np.minimum(weight[idx], np.repeat(bow.weights, cnt))
            out += np.bincount(slot[idx], weights=contrib, minlength=n_slots)
        return out


@dataclass(frozen=True)
class QueryScores:
    """Scores of a query against database keyframes: kf_ids (K,) int64, s_points, s_lines, combined (K,)."""

    kf_ids: np.ndarray
    s_points: np.ndarray
    s_lines: np.ndarray
    combined: np.ndarray


class KeyframeDatabase:
    """Point and line BoW vectors of keyframes with one inverted index per vocabulary.

    keep_bows: how many of the newest keyframes keep their BoW vectors for `bows` (None: all). The inverted index
    holds every keyframe's words for queries; the vectors themselves are only asked for the newest few (the
    neighbour score), so a long run need not keep a second copy of every keyframe's."""

    def __init__(self, keep_bows: int | None = None) -> None:
        self._ids: list[int] = []
        self._slot: dict[int, int] = {}
        self._keep_bows = keep_bows
        self._bows: dict[int, tuple[BowVector, BowVector]] = {}
        self._has_lines = np.zeros(0, bool)
        self._points = _InvertedIndex()
        self._lines = _InvertedIndex()

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._slot

    def add(self, kf_id: int, bow_points: BowVector, bow_lines: BowVector) -> None:
        if kf_id in self._slot:
            raise ValueError(f"keyframe database: keyframe {kf_id} already added")
        slot = len(self._ids)
        self._ids.append(int(kf_id))
        self._slot[int(kf_id)] = slot
        self._bows[slot] = (bow_points, bow_lines)
        if self._keep_bows is not None and slot - self._keep_bows in self._bows:
            del self._bows[slot - self._keep_bows]
        self._has_lines = np.append(self._has_lines, len(bow_lines) > 0)
        self._points.add(slot, bow_points)
        self._lines.add(slot, bow_lines)

    def bows(self, kf_id: int) -> tuple[BowVector, BowVector]:
        try:
            return self._bows[self._slot[kf_id]]
        except KeyError:
            raise KeyError(f"keyframe database: no BoW vectors kept for keyframe {kf_id} (the newest "
                           f"{self._keep_bows} keep theirs)") from None

    def query(self, bow_points: BowVector, bow_lines: BowVector, max_id: int | None = None) -> QueryScores:
        """Scores of every keyframe with id <= max_id (all when None) that shares a word with the query."""
        n = len(self._ids)
        ids = np.asarray(self._ids, dtype=np.int64)
        sp = self._points.scores(bow_points, n)
        sl = self._lines.scores(bow_lines, n)
        keep = (sp > 0) | (sl > 0)
        if max_id is not None:
            keep &= ids <= max_id
        no_lines = ~self._has_lines | (len(bow_lines) == 0)
        sl_eff = np.where(no_lines, sp, sl)
        return QueryScores(ids[keep], sp[keep], sl[keep], combine_scores(sp[keep], sl_eff[keep]))

    def pair_score(self, a: tuple[BowVector, BowVector], b: tuple[BowVector, BowVector]) -> float:
        """Combined score of two (point, line) BoW pairs."""
        sp = l1_score(a[0], b[0])
        sl = sp if (len(a[1]) == 0 or len(b[1]) == 0) else l1_score(a[1], b[1])
        return float(combine_scores(sp, sl))


@dataclass(frozen=True)
class Detection:
    """Outcome of one loop query.

    kf_id: the query keyframe; candidates (C,) int64 keyframe ids with raw combined scores (C,) and normalised
    scores (C,) (score / best neighbour score), best first, only those above LoopConfig.min_score;
    neighbour_score: the normaliser; island (lo, hi) of keyframe ids or None; consistency: how many consecutive
    queries agreed on this island; ready: consistency reached (candidates should be verified); to_verify: the
    ids to check, best first; reason: why not ready ("" when ready).
    """

    kf_id: int
    candidates: np.ndarray
    scores: np.ndarray
    normalised: np.ndarray
    neighbour_score: float
    island: tuple[int, int] | None
    consistency: int
    ready: bool
    to_verify: tuple[int, ...] = ()
    reason: str = ""
    n_scored: int = field(default=0)


def _islands(ids: np.ndarray, eta: np.ndarray, gap: int) -> list[tuple[int, int, float, np.ndarray]]:
    """Group candidate ids (sorted ascending) into runs no more than `gap` apart -> (lo, hi, sum eta, members)."""
    out = []
    start = 0
    for i in range(1, len(ids) + 1):
        if i == len(ids) or ids[i] - ids[i - 1] > gap:
            members = np.arange(start, i)
            out.append((int(ids[start]), int(ids[i - 1]), float(eta[members].sum()), members))
            start = i
    return out


class LoopDetector:
    """Stateful DBoW2-style detector over a KeyframeDatabase: call `detect` then `add` for every keyframe."""

    def __init__(self, cfg: LoopConfig | None = None) -> None:
        self.cfg = cfg or LoopConfig()
        self.db = KeyframeDatabase(keep_bows=max(1, self.cfg.neighbours))
        self._order: list[int] = []  # keyframe ids in arrival order
        self._last_island: tuple[int, int] | None = None
        self._count = 0

    def add(self, kf_id: int, bow_points: BowVector, bow_lines: BowVector) -> None:
        self.db.add(kf_id, bow_points, bow_lines)
        self._order.append(int(kf_id))

    def _neighbour_score(self, query: tuple[BowVector, BowVector]) -> float:
        prev = self._order[-max(1, self.cfg.neighbours):]
        return max((self.db.pair_score(query, self.db.bows(p)) for p in prev), default=0.0)

    def _fail(self, kf_id: int, reason: str, nb: float = 0.0, n_scored: int = 0) -> Detection:
        self._last_island, self._count = None, 0
        empty = np.zeros(0)
        return Detection(kf_id, empty.astype(np.int64), empty, empty, nb, None, 0, False, (), reason, n_scored)

    def detect(self, kf_id: int, bow_points: BowVector, bow_lines: BowVector) -> Detection:
        """Query before adding keyframe kf_id; candidates exclude the last cfg.min_keyframe_gap keyframes."""
        cfg = self.cfg
        if len(self._order) <= cfg.min_keyframe_gap:
            return self._fail(kf_id, f"only {len(self._order)} keyframes in the database")
        nb = self._neighbour_score((bow_points, bow_lines))
        if nb < cfg.min_neighbour_score:
            return self._fail(kf_id, f"previous keyframe scores only {nb:.4f}", nb)
        max_id = self._order[-cfg.min_keyframe_gap - 1]
        q = self.db.query(bow_points, bow_lines, max_id=max_id)
        eta = q.combined / nb
        ok = eta >= cfg.min_score
        if not ok.any():
            best = float(eta.max()) if len(eta) else 0.0
            return self._fail(kf_id, f"no candidate above {cfg.min_score} (best normalised {best:.3f})", nb,
                              len(eta))
        ids, raw, eta = q.kf_ids[ok], q.combined[ok], eta[ok]
        order = np.argsort(ids)
        ids, raw, eta = ids[order], raw[order], eta[order]
        lo, hi, _, members = max(_islands(ids, eta, cfg.island_gap), key=lambda isl: isl[2])
        if self._last_island is not None and _near(self._last_island, (lo, hi), cfg.island_gap):
            self._count += 1
        else:
            self._count = 1
        self._last_island = (lo, hi)
        best_first = np.argsort(-eta)
        in_island = members[np.argsort(-eta[members])]
        to_verify = tuple(int(ids[i]) for i in in_island[: cfg.max_verify])
        ready = self._count >= cfg.consistency
        reason = "" if ready else f"island {lo}-{hi} consistent over {self._count}/{cfg.consistency} keyframes"
        return Detection(kf_id, ids[best_first], raw[best_first], eta[best_first], nb, (lo, hi), self._count,
                         ready, to_verify if ready else (), reason, len(q.kf_ids))


def _near(a: tuple[int, int], b: tuple[int, int], gap: int) -> bool:
    """Do id ranges a and b overlap or lie within `gap` of each other?"""
    return a[0] - gap <= b[1] and b[0] - gap <= a[1]
