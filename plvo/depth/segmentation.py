"""Foreground/background segmentation of the lidar points in a feature's patch, batched over patches.

What we chose, after Tateno et al. (IROS 2015), whose segments are bounded by depth discontinuities (a neighbour
far from a point's tangent plane) and concave edges, for a patch of a few dozen sparse points:

1. Depth discontinuity. The patch's depths are sorted and cut at every gap larger than
   max(depth_jump_min_m, depth_jump_ratio * z): clusters 0, 1, ... from near to far. The foreground seed is the
   nearest cluster, so a feature on an occluding edge (a pole in front of a wall) takes the pole's depth.
2. Surface continuity (Tateno's normal-distance test). A depth gap is not an object boundary when the points on
   both sides lie on one surface: the road or a wall seen at a slant gives one cluster per scan ring. The
   foreground grows over gap k -> k+1 when clusters 0..k+1 together are planar (RMS distance to their plane at
   most plane_max_rms_m) and that plane is not grazing for the feature's ray, and stops at the first gap that
   fails. A pole and the wall behind it are never one plane, so they are never mixed.
3. Convexity. Within the foreground, a concave fold (wall meeting ground) is two surfaces; the robust plane fit
   in points.py keeps the face that holds most of the points near the feature and rejects the other face's points
   as outliers, which plays the part of Tateno's concavity cut at this patch size.
"""

from __future__ import annotations

import numpy as np

MAX_CLUSTERS = 4  # depth clusters considered for the foreground (a 15 px patch spans at most ~4 scan rings)


def depth_clusters(depth: np.ndarray, jump_ratio: float, jump_min_m: float) -> np.ndarray:
    """(Q,P) depths, NaN padding -> (Q,P) int cluster labels, 0 nearest, -1 on padding."""
    z = np.where(np.isfinite(depth), depth, np.inf)
    order = np.argsort(z, axis=1)
    zs = np.take_along_axis(z, order, axis=1)
    with np.errstate(invalid="ignore"):
        gaps = np.diff(zs, axis=1)  # inf - inf on padding gives NaN: never a break
        brk = gaps > np.maximum(jump_min_m, jump_ratio * zs[:, :-1])
    lab_sorted = np.concatenate([np.zeros((len(z), 1), dtype=np.int64), np.cumsum(brk, axis=1)], axis=1)
    lab_sorted[~np.isfinite(zs)] = -1
    labels = np.empty_like(lab_sorted)
    np.put_along_axis(labels, order, lab_sorted, axis=1)
    return labels


def fit_planes(pts: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(Q,P,3) points (any finite value on padding), (Q,P) weights -> normals (Q,3), offsets (Q,) with
    n.x + d = 0, eigenvalues ascending (Q,3), weighted centroids (Q,3).

    Weighted total least squares: the normal is the eigenvector of the smallest eigenvalue of the weighted
    covariance, so sqrt(eig[:,0]) is the weighted RMS distance to the plane. Rows with zero weight give NaN.
    """
    X, Y, Z = (np.ascontiguousarray(pts[..., k]) for k in range(3))
    return fit_planes_xyz(X, Y, Z, w)


def fit_planes_xyz(
    X: np.ndarray, Y: np.ndarray, Z: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """fit_planes on coordinates given as three contiguous (Q,P) arrays (several times faster than (Q,P,3))."""
    sw = w.sum(axis=1)
    bad = sw <= 0
    inv = 1.0 / np.where(bad, 1.0, sw)
    wx, wy, wz = w * X, w * Y, w * Z
    cx, cy, cz = wx.sum(1) * inv, wy.sum(1) * inv, wz.sum(1) * inv
    # Second moments about the centroid, from raw sums (six unique entries); patches span metres, so the
    # cancellation error is far below the lidar noise.
    axx = np.einsum("qp,qp->q", wx, X) * inv - cx * cx
    ayy = np.einsum("qp,qp->q", wy, Y) * inv - cy * cy
    azz = np.einsum("qp,qp->q", wz, Z) * inv - cz * cz
    axy = np.einsum("qp,qp->q", wx, Y) * inv - cx * cy
    axz = np.einsum("qp,qp->q", wx, Z) * inv - cx * cz
    ayz = np.einsum("qp,qp->q", wy, Z) * inv - cy * cz
    eig, n = sym3_smallest(axx, ayy, azz, axy, axz, ayz)
    c = np.stack([cx, cy, cz], axis=1)
    d = -(n[:, 0] * cx + n[:, 1] * cy + n[:, 2] * cz)
    if bad.any():
        n[bad], d[bad], eig[bad], c[bad] = np.nan, np.nan, np.nan, np.nan
    return n, d, np.maximum(eig, 0.0), c


def sym3_smallest(
    a00: np.ndarray, a11: np.ndarray, a22: np.ndarray, a01: np.ndarray, a02: np.ndarray, a12: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric 3x3 matrices by their six (Q,) entries -> eigenvalues ascending (Q,3), unit eigenvector of the
    smallest (Q,3).

    Closed form (trigonometric solution of the characteristic cubic) on entry arrays: ~10x faster than batched
    eigh, and several times faster than the same on (Q,3,3) arrays.
    """
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
    ip = 1.0 / np.where(p > 1e-300, p, 1.0)
    b00, b11, b22, b01, b02, b12 = b00 * ip, b11 * ip, b22 * ip, a01 * ip, a02 * ip, a12 * ip
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    e_max = q + 2.0 * p * np.cos(phi)
    e_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    eig = np.stack([e_min, 3.0 * q - e_max - e_min, e_max], axis=1)
    # rows of A - e_min I; the eigenvector is the largest of their pairwise cross products
    m00, m11, m22 = a00 - e_min, a11 - e_min, a22 - e_min
    r0, r1, r2 = (m00, a01, a02), (a01, m11, a12), (a02, a12, m22)
    cands = np.stack([_cross3(r0, r1), _cross3(r0, r2), _cross3(r1, r2)], axis=1)  # (Q,3 cand,3)
    norms = np.sqrt(np.einsum("qki,qki->qk", cands, cands))
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(q))
    v = cands[rows, best]
    nv = norms[rows, best]
    v = v / np.where(nv > 0, nv, 1.0)[:, None]
    v[nv <= 0] = np.array([0.0, 0.0, 1.0])
    return eig, v


def _cross3(a: tuple, b: tuple) -> np.ndarray:
    """Cross product of two vectors given as 3-tuples of (Q,) arrays -> (Q,3)."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]], axis=1)


def grow_foreground(
    pts: np.ndarray,
    labels: np.ndarray,
    rays: np.ndarray,
    max_rms: float,
    min_cos: float,
    min_spread_ratio: float = 0.1,
) -> np.ndarray:
    """(Q,P,3) camera points, (Q,P) depth labels, (Q,3) unit feature rays -> (Q,) last cluster k of the foreground.

    The foreground is clusters 0..k. Gap j -> j+1 is bridged while clusters 0..j+1 are planar, non-degenerate (a
    spread in two directions, not one scan ring) and seen by the ray at a non-grazing angle.
    """
    X, Y, Z = (np.ascontiguousarray(pts[..., k]) for k in range(3))
    return grow_foreground_xyz(X, Y, Z, labels, rays, max_rms, min_cos, min_spread_ratio)


def grow_foreground_xyz(
    X: np.ndarray,
    Y: np.ndarray,
    Z: np.ndarray,
    labels: np.ndarray,
    rays: np.ndarray,
    max_rms: float,
    min_cos: float,
    min_spread_ratio: float = 0.1,
) -> np.ndarray:
    """grow_foreground on coordinates given as three contiguous (Q,P) arrays."""
    Q = len(X)
    k_sel = np.zeros(Q, dtype=np.int64)
    alive = np.ones(Q, dtype=bool)
    n_clusters = labels.max(axis=1, initial=-1) + 1
    for k in range(1, MAX_CLUSTERS):
        alive &= n_clusters > k
        if not alive.any():
            break
        q = np.flatnonzero(alive)
        lq = labels[q]
        m = ((lq >= 0) & (lq <= k)).astype(float)
        n, _, eig, _ = fit_planes_xyz(X[q], Y[q], Z[q], m)
        with np.errstate(invalid="ignore", divide="ignore"):
            planar = np.sqrt(eig[:, 0]) <= max_rms
            spread = np.sqrt(eig[:, 1]) >= min_spread_ratio * np.sqrt(eig[:, 2])
            facing = np.abs(np.einsum("qi,qi->q", n, rays[q])) >= min_cos
        ok = planar & spread & facing
        k_sel[q[ok]] = k
        alive[q[~ok]] = False
    return k_sel


def foreground_mask(labels: np.ndarray, k_sel: np.ndarray) -> np.ndarray:
    """(Q,P) labels, (Q,) last foreground cluster -> (Q,P) bool foreground."""
    return (labels >= 0) & (labels <= k_sel[:, None])
