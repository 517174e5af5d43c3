"""3D lines: Pluecker coordinates, the orthonormal 4-dof representation, transformation and projection.

A line is a (6,) array L = [m, d]: d its direction, m = p x d its moment (p any point of the line). It is
homogeneous: any nonzero multiple is the same line. Batch forms take (N,6). `plucker_from_points` returns lines
scaled to |d| = 1, so that |m| is the distance to the origin.

The orthonormal representation (Bartoli & Sturm 2005, used by Zuo et al. 2017 / PL-SLAM) writes the 3x2 matrix
[m | d] = U diag(w1, w2) (first two columns), U in SO(3), (w1, w2) = first column of W in SO(2); it is updated
minimally by `orth_update` with a 4-vector delta. Projection follows Zhang et al. 2015: the image line is
l = K_L m with K_L the line projection matrix, and the reprojection residual is the paper's gamma.

Analytic Jacobians live in `line_jacobians.py`, which builds on this module.
"""

from __future__ import annotations

import numpy as np

from plvo.errors import PlvoError

_TINY = 1e-12


def _as_lines(L: np.ndarray, name: str = "L") -> tuple[np.ndarray, bool]:
    """(6,) or (N,6) -> (N,6) float and whether the input was a single line."""
    arr = np.asarray(L, dtype=float)
    if arr.shape == (6,):
        return arr[None, :], True
    if arr.ndim != 2 or arr.shape[1] != 6:
        raise PlvoError(f"lines: {name} must have shape (6,) or (N,6), got {arr.shape}")
    return arr, False


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross on (N,3) is slow-ish and warns on 2-vectors in numpy 2; spell it out.
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def hat_batch(w: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) skew matrices."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _so3_exp_batch(phi: np.ndarray) -> np.ndarray:
    """(N,3) rotation vectors -> (N,3,3) rotations (Rodrigues, series near 0)."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-3
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    W = hat_batch(phi)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def plucker_from_points(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(3,),(3,) -> (6,) or (N,3),(N,3) -> (N,6): the line through p and q (any frame), scaled to |d| = 1."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    single = p.ndim == 1
    p2, q2 = np.atleast_2d(p), np.atleast_2d(q)
    if p2.shape != q2.shape or p2.shape[1] != 3:
        raise PlvoError(f"plucker_from_points: p and q must both be (3,) or (N,3), got {p.shape} and {q.shape}")
    d = q2 - p2
    n = np.linalg.norm(d, axis=1)
    bad = n <= _TINY * np.maximum(1.0, np.linalg.norm(p2, axis=1))
    if np.any(bad):
        raise PlvoError(f"plucker_from_points: p and q coincide at rows {np.flatnonzero(bad)[:10].tolist()}")
    d = d / n[:, None]
    L = np.concatenate([cross3(p2, d), d], axis=1)
    return L[0] if single else L


def line_direction(L: np.ndarray) -> np.ndarray:
    """(6,) -> (3,) or (N,6) -> (N,3): unit direction d / |d| (same frame as L)."""
    arr, single = _as_lines(L)
    d = arr[:, 3:] / np.linalg.norm(arr[:, 3:], axis=1, keepdims=True)
    return d[0] if single else d


def closest_point_to_origin(L: np.ndarray) -> np.ndarray:
    """(6,) -> (3,) or (N,6) -> (N,3): the point of the line nearest the frame's origin, (d x m) / |d|^2."""
    arr, single = _as_lines(L)
    m, d = arr[:, :3], arr[:, 3:]
    p = cross3(d, m) / np.sum(d * d, axis=1, keepdims=True)
    return p[0] if single else p


def plucker_to_orth(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(6,) -> (U (3,3), W (2,2)) or (N,6) -> ((N,3,3), (N,2,2)): orthonormal representation, same frame as L.

    U = [m/|m|, d/|d|, (m x d)/|m x d|], W = [[w1, -w2], [w2, w1]] with (w1, w2) = (|m|, |d|) / |(|m|, |d|)|.
    A line through the origin (m = 0) gets w1 = 0 and an arbitrary first column of U perpendicular to d.
    """
    arr, single = _as_lines(L)
    m, d = arr[:, :3], arr[:, 3:]
    nm, nd = np.linalg.norm(m, axis=1), np.linalg.norm(d, axis=1)
    if np.any(nd <= _TINY):
        raise PlvoError("plucker_to_orth: L has a zero direction d (not a line)")
    u2 = d / nd[:, None]
    # Re-orthogonalise m against d: Pluecker vectors from noisy sources drift off the Klein quadric.
    m_perp = m - np.sum(m * u2, axis=1, keepdims=True) * u2
    nmp = np.linalg.norm(m_perp, axis=1)
    through_origin = nmp <= _TINY * nd
    if np.any(through_origin):
        # Any unit vector perpendicular to d: cross with the world axis least aligned with it.
        axis = np.eye(3)[np.argmin(np.abs(u2[through_origin]), axis=1)]
        m_perp[through_origin] = cross3(u2[through_origin], axis)
        nmp[through_origin] = np.linalg.norm(m_perp[through_origin], axis=1)
        nm = np.where(through_origin, 0.0, nm)
    u1 = m_perp / nmp[:, None]
    U = np.stack([u1, u2, cross3(u1, u2)], axis=2)
    s = np.hypot(nm, nd)
    w1, w2 = nm / s, nd / s
    W = np.stack([np.stack([w1, -w2], axis=1), np.stack([w2, w1], axis=1)], axis=1)
    return (U[0], W[0]) if single else (U, W)


def orth_to_plucker(U: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(3,3),(2,2) -> (6,) or (N,3,3),(N,2,2) -> (N,6): L = [w1 u1, w2 u2], |L| = 1, frame of U."""
    U = np.asarray(U, dtype=float)
    W = np.asarray(W, dtype=float)
    L = np.concatenate([W[..., 0, 0, None] * U[..., :, 0], W[..., 1, 0, None] * U[..., :, 1]], axis=-1)
    return L


def orth_update(U: np.ndarray, W: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,3),(2,2),(4,) -> (U', W') (or batch (N,3,3),(N,2,2),(N,4)): U' = U exp(delta[:3]), W' = W R2(delta[3])."""
    U = np.asarray(U, dtype=float)
    W = np.asarray(W, dtype=float)
    delta = np.asarray(delta, dtype=float)
    c, s = np.cos(delta[..., 3]), np.sin(delta[..., 3])
    R2 = np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)
    return U @ _so3_exp_batch(delta[..., :3]), W @ R2


def transform_line(T_a_b: np.ndarray, L_b: np.ndarray) -> np.ndarray:
    """(4,4) or (N,4,4) pose, (6,) or (N,6) line in frame b -> line in frame a: [R m + t x (R d), R d]."""
    arr, single = _as_lines(L_b, "L_b")
    T = np.asarray(T_a_b, dtype=float)
    R, t = T[..., :3, :3], T[..., :3, 3]
    d = np.einsum("...ij,...j->...i", R, arr[:, 3:])
    m = np.einsum("...ij,...j->...i", R, arr[:, :3]) + cross3(np.broadcast_to(t, d.shape), d)
    out = np.concatenate([m, d], axis=-1)
    return out[0] if single and T.ndim == 2 else out


def line_projection_matrix(K: np.ndarray) -> np.ndarray:
    """(3,3) camera matrix -> (3,3) K_L = [[fy,0,0],[0,fx,0],[-fy cx,-fx cy,fx fy]] (= fx fy K^-T, no skew)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[fy, 0.0, 0.0], [0.0, fx, 0.0], [-fy * cx, -fx * cy, fx * fy]])


def project_line(K: np.ndarray, L_cam: np.ndarray) -> np.ndarray:
    """(3,3), (6,) or (N,6) camera-frame line -> (3,) or (N,3) image line l, l1 u + l2 v + l3 = 0 (pixels).

    Only the moment enters: l = K_L m. A line through the camera centre (m = 0) projects to a point and gives l = 0.
    """
    arr, single = _as_lines(L_cam, "L_cam")
    l = arr[:, :3] @ line_projection_matrix(K).T
    return l[0] if single else l


def line_reprojection_residual(l: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """(3,),(4,) -> (2,) or (N,3),(N,4) -> (N,2): signed pixel distances of segment ends (x1,y1,x2,y2) to l.

    The sign follows l's orientation (flipping l flips both). A degenerate l (l1 = l2 = 0) gives inf/nan.
    """
    l = np.asarray(l, dtype=float)
    seg = np.asarray(segment, dtype=float)
    single = l.ndim == 1
    l2, s2 = np.atleast_2d(l), np.atleast_2d(seg)
    norm = np.hypot(l2[:, 0], l2[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = (l2[:, 0] * s2[:, 0] + l2[:, 1] * s2[:, 1] + l2[:, 2]) / norm
        r2 = (l2[:, 0] * s2[:, 2] + l2[:, 1] * s2[:, 3] + l2[:, 2]) / norm
    r = np.stack([r1, r2], axis=1)
    return r[0] if single else r


def point_line_distance(points: np.ndarray, L: np.ndarray) -> np.ndarray:
    """(N,3) points, (6,) line, both in the same frame -> (N,) Euclidean distances |p x d - m| / |d| (metres)."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    L = np.asarray(L, dtype=float).reshape(6)
    m, d = L[:3], L[3:]
    e = cross3(pts, np.broadcast_to(d, pts.shape)) - m
    return np.linalg.norm(e, axis=1) / np.linalg.norm(d)


def trim_endpoints(K: np.ndarray, L_cam: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """(3,3), (6,) camera-frame line, (4,) segment (x1,y1,x2,y2) -> (2,3) camera-frame 3D endpoints.

    Each endpoint is the point of the 3D line closest to the back-projected ray of that segment end. When a ray
    is parallel to the line (sin of their angle below 1e-9: the end sits on the line's vanishing point, its depth
    is infinite and every point of the line is equally close) that row is NaN; callers filter with np.isfinite.
    """
    L = np.asarray(L_cam, dtype=float).reshape(6)
    seg = np.asarray(segment, dtype=float).reshape(2, 2)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rays = np.stack([(seg[:, 0] - cx) / fx, (seg[:, 1] - cy) / fy, np.ones(2)], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    d = L[3:] / np.linalg.norm(L[3:])
    p0 = closest_point_to_origin(L)
    # Closest points of p0 + t d and s r: minimise |p0 + t d - s r|^2 over (t, s), with |d| = |r| = 1.
    b = rays @ d
    e = rays @ p0
    # |r x d|^2 = 1 - b^2, but without the cancellation that hides near-parallel rays.
    denom = np.sum(cross3(rays, np.broadcast_to(d, rays.shape)) ** 2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (b * e - (d @ p0)) / denom
    t = np.where(denom > 1e-18, t, np.nan)
    return p0 + t[:, None] * d

