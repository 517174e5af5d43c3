"""Bag-of-words vocabulary for 256-bit binary descriptors (ORB, LBD), built as DBoW2 builds its vocabularies.

A hierarchical k-majority tree: every node's descriptors are split into k clusters by k-means on Hamming distance
(k-means++ seeding, majority-vote centroids: a centroid bit is set when at least half of the members have it),
down to `depth` levels; the leaves are the words. Each word carries an IDF weight log(N_images / n_images_with_word)
learned from the training images; an image becomes a sparse TF-IDF vector, L1-normalised, and two vectors are
compared with DBoW2's L1 score s = 1 - 0.5 |v1 - v2|_1 in [0, 1] (for non-negative L1-normalised vectors this
equals the sum over shared words of min(v1_w, v2_w), which is how it is computed).

Everything is vectorised over descriptors: a descriptor is viewed as four uint64 words and the Hamming distance
is `np.bitwise_count(a ^ b).sum()`. The tree is stored as flat arrays (node centroids, child table, word of leaf,
IDF) in an .npz file.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plvo.atomic import atomic_path
from plvo.errors import PlvoError

log = logging.getLogger(__name__)

DESC_BYTES = 32  # ORB and LBD descriptors are both 256 bits
FORMAT_VERSION = 1


@dataclass(frozen=True)
class BowVector:
    """Sparse L1-normalised TF-IDF vector: words (W,) int32 sorted ascending, weights (W,) float64 summing to 1."""

    words: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return int(len(self.words))


EMPTY_BOW = BowVector(np.zeros(0, np.int32), np.zeros(0))


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 score 1 - 0.5 |a - b|_1 of two L1-normalised vectors, in [0, 1] (1 for identical vectors)."""
    if len(a) == 0 or len(b) == 0:
        return 0.0
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


def _as_u64(desc: np.ndarray, what: str) -> np.ndarray:
    desc = np.asarray(desc)
    if desc.ndim != 2 or desc.shape[1] != DESC_BYTES or desc.dtype != np.uint8:
        raise PlvoError(f"vocabulary: field '{what}' must be (N,{DESC_BYTES}) uint8, got {desc.shape} {desc.dtype}")
    return np.ascontiguousarray(desc).view(np.uint64)


def hamming(a_u64: np.ndarray, b_u64: np.ndarray) -> np.ndarray:
    """Hamming distances of (N,4) uint64 descriptors against (K,4) -> (N,K) int32."""
    b = np.bitwise_count(a_u64[:, None, :] ^ b_u64[None, :, :])
    return (b[..., 0] + b[..., 1] + b[..., 2] + b[..., 3]).astype(np.int32)


def _majority(bits: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Majority-vote centroids of unpacked (n,256) bits grouped by labels (n,) in [0,k) -> (k,32) uint8."""
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels, minlength=k)
    ends = np.cumsum(counts)
    grouped = bits[order]
    # Summing contiguous row blocks is ~15x faster than np.add.reduceat over (n,256) uint8.
    sums = np.stack([grouped[e - c:e].sum(0, dtype=np.int32) for c, e in zip(counts, ends)])
    return np.packbits(2 * sums >= counts[:, None], axis=1)


def _kmeans(desc: np.ndarray, bits: np.ndarray, k: int, rng: np.random.Generator, max_iter: int) -> np.ndarray:
    """k-majority clustering of (n,32) uint8 descriptors (n > k); returns labels (n,) in [0, k') for k' <= k."""
    u64 = desc.view(np.uint64)
    n = len(desc)
    # k-means++ seeding on Hamming distance (DBoW2's initiateClustersKMpp draws proportionally to distance).
    centres = [int(rng.integers(n))]
    min_d = hamming(u64, u64[centres[0]][None])[:, 0].astype(np.float64)
    for _ in range(k - 1):
        total = min_d.sum()
        if total <= 0:
            break  # every descriptor equals a centre already
        nxt = min(int(np.searchsorted(np.cumsum(min_d), rng.random() * total, side="right")), n - 1)
        centres.append(nxt)
        min_d = np.minimum(min_d, hamming(u64, u64[nxt][None])[:, 0])
    cent = desc[centres]
    labels: np.ndarray | None = None
    for _ in range(max_iter):
        new = np.argmin(hamming(u64, cent.view(np.uint64)), axis=1)
        if labels is not None and np.array_equal(new, labels):
            break
        # Drop empty clusters so labels stay dense in [0, k').
        used = np.bincount(new, minlength=len(cent)) > 0
        labels = (np.cumsum(used) - 1)[new]
        cent = _majority(bits, labels, int(used.sum()))
    assert labels is not None  # iterations >= 1
    return labels


class Vocabulary:
    """A trained tree. Build with `Vocabulary.train`, persist with `save` / `Vocabulary.load`."""

    def __init__(self, node_desc: np.ndarray, children: np.ndarray, node_word: np.ndarray, idf: np.ndarray,
                 depth: int, info: str = "") -> None:
        self.node_desc = np.ascontiguousarray(node_desc, dtype=np.uint8)
        self.children = np.asarray(children, dtype=np.int32)
        # (nodes, k, 4) uint64 centroids of each node's children: one contiguous np.take a level in words_of.
        self._child_u64 = self.node_desc.view(np.uint64)[np.maximum(self.children, 0)]
        self._child_bad = self.children < 0
        self.node_word = np.asarray(node_word, dtype=np.int32)
        self.idf = np.asarray(idf, dtype=np.float64)
        self.depth = int(depth)
        self.info = str(info)

    @property
    def k(self) -> int:
        return int(self.children.shape[1])

    @property
    def n_words(self) -> int:
        return int(len(self.idf))

    def __repr__(self) -> str:
        return f"Vocabulary(k={self.k}, depth={self.depth}, words={self.n_words}, nodes={len(self.node_desc)})"

    # -- use -------------------------------------------------------------------------------------------------

    def words_of(self, desc: np.ndarray) -> np.ndarray:
        """(N,32) uint8 descriptors -> (N,) int32 word ids, by greedy descent of the tree (as DBoW2)."""
        u64 = _as_u64(desc, "descriptors")
        cur = np.zeros(len(u64), np.int64)
        for _ in range(self.depth):
            ch = self.children[cur]
            idx = np.nonzero(ch[:, 0] >= 0)[0]
            if len(idx) == 0:
                break
            ch, node = ch[idx], cur[idx]
            b = np.bitwise_count(np.take(self._child_u64, node, axis=0) ^ u64[idx, None, :])
            d = b[..., 0] + b[..., 1] + b[..., 2] + b[..., 3]
            d[np.take(self._child_bad, node, axis=0)] = 255
            cur[idx] = ch[np.arange(len(idx)), np.argmin(d, axis=1)]
        return self.node_word[cur]

    def transform(self, desc: np.ndarray) -> BowVector:
        """(N,32) uint8 descriptors -> L1-normalised TF-IDF BowVector (empty when N == 0)."""
        if len(desc) == 0:
            return EMPTY_BOW
        return self.bow_from_words(self.words_of(desc))

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        """(N,) word ids of one image's descriptors -> its L1-normalised TF-IDF BowVector."""
        # TF-IDF: every occurrence adds the word's IDF; the 1/N of the term frequency disappears in the L1 norm.
        acc = np.bincount(words, weights=self.idf[words], minlength=self.n_words)
        ids = np.nonzero(acc > 0)[0]
        total = acc[ids].sum()
        if total <= 0:
            return EMPTY_BOW
        return BowVector(ids.astype(np.int32), acc[ids] / total)

    def score(self, a: BowVector, b: BowVector) -> float:
        return l1_score(a, b)

    # -- training --------------------------------------------------------------------------------------------

    @classmethod
    def train(cls, images: Sequence[np.ndarray], k: int = 10, depth: int = 5, seed: int = 0, max_iter: int = 10,
              progress: Callable[[int], None] | None = None, info: str = "") -> Vocabulary:
        """Build from per-image (N_i,32) uint8 descriptor arrays; progress(n) is told of n descriptors placed."""
        if k < 2 or depth < 1:
            raise PlvoError(f"vocabulary: need k >= 2 and depth >= 1, got k={k} depth={depth}")
        arrays = [np.asarray(d) for d in images if len(d)]
        if not arrays:
            raise PlvoError("vocabulary: field 'images' holds no descriptors to train on")
        desc = np.concatenate([_as_u64(d, "images[i]").view(np.uint8) for d in arrays])
        bits = np.unpackbits(desc, axis=1)
        rng = np.random.default_rng(seed)
        node_desc = [np.zeros(DESC_BYTES, np.uint8)]
        children: list[list[int]] = [[]]
        queue = deque([(0, np.arange(len(desc)), 0)])  # (node, member indices, level), breadth first
        while queue:
            node, members, level = queue.popleft()
            if level >= depth or len(members) <= 1:
                if progress:
                    progress(len(members))
                continue
            sub = desc[members]
            if len(members) <= k:  # DBoW2: a node with at most k descriptors gets one child each
                labels, cents = np.arange(len(members)), sub
            else:
                labels = _kmeans(sub, bits[members], k, rng, max_iter)
                cents = _majority(bits[members], labels, int(labels.max()) + 1)
            for c in range(len(cents)):
                child = len(node_desc)
                node_desc.append(cents[c])
                children.append([])
                children[node].append(child)
                queue.append((child, members[labels == c], level + 1))
        vocab = cls._from_lists(node_desc, children, k, depth, info)
        vocab._learn_idf(arrays)
        log.info("trained %r on %d descriptors of %d images", vocab, len(desc), len(arrays))
        return vocab

    @classmethod
    def _from_lists(cls, node_desc: list[np.ndarray], children: list[list[int]], k: int, depth: int,
                    info: str) -> Vocabulary:
        n = len(node_desc)
        table = np.full((n, k), -1, np.int32)
        for i, ch in enumerate(children):
            table[i, : len(ch)] = ch
        leaf = table[:, 0] < 0
        leaf[0] = n == 1
        node_word = np.full(n, -1, np.int32)
        node_word[leaf] = np.arange(int(leaf.sum()), dtype=np.int32)
        return cls(np.stack(node_desc), table, node_word, np.ones(int(leaf.sum())), depth, info)

    def _learn_idf(self, images: Sequence[np.ndarray]) -> None:
        seen = np.zeros(self.n_words, np.int64)
        for d in images:
            seen[np.unique(self.words_of(d))] += 1
        # DBoW2: words never seen in training keep weight 0.
        self.idf = np.where(seen > 0, np.log(len(images) / np.maximum(seen, 1)), 0.0)

    # -- persistence -----------------------------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write the tree as compressed arrays to an .npz file, atomically."""
        path = Path(path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, version=FORMAT_VERSION, node_desc=self.node_desc, children=self.children,
                                    node_word=self.node_word, idf=self.idf, depth=self.depth, info=self.info)
            tmp.chmod(0o644)  # mkstemp makes 0600; vocabularies are shipped and shared

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                if int(z["version"]) != FORMAT_VERSION:
                    raise PlvoError(f"{path}: field 'version' is {int(z['version'])}, expected {FORMAT_VERSION}")
                return cls(z["node_desc"], z["children"], z["node_word"], z["idf"], int(z["depth"]), str(z["info"]))
        except (OSError, KeyError, ValueError) as exc:
            raise PlvoError(f"{path}: not a readable vocabulary file ({exc})") from exc


ASSET_DIR = Path(__file__).resolve().parents[1] / "assets" / "vocab"


def load_default(kind: str) -> Vocabulary:
    """The shipped vocabulary: kind 'orb' or 'lbd' (plvo/assets/vocab/<kind>.npz)."""
    path = ASSET_DIR / f"{kind}.npz"
    if not path.is_file():
        raise PlvoError(f"{path}: shipped {kind} vocabulary missing (train one with `plvo vocab`)")
    return Vocabulary.load(path)
