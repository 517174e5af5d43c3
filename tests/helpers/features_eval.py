"""Ground-truth judges of feature matches, shared by the feature tests and the measurement script.

Points: a match is right when its Sampson (first-order epipolar) distance under the ground-truth relative pose is
under a bound and the two-view triangulation lies in front of both cameras.
Lines: two-view geometry does not constrain an infinite line, so a line match is judged on its endpoints: the
epipolar lines of the current segment's endpoints must cut the previous segment's line inside (or near) the
previous segment, in front of both cameras. Segments within 10 deg of the epipolar direction cannot be judged.
"""

from __future__ import annotations

import numpy as np


def skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def fundamental(K: np.ndarray, T_1_0: np.ndarray) -> np.ndarray:
    """F with x1^T F x0 = 0 for cameras related by T_1_0 (maps cam-0 points into cam 1)."""
    E = skew(T_1_0[:3, 3]) @ T_1_0[:3, :3]
    Ki = np.linalg.inv(K)
    return Ki.T @ E @ Ki


def sampson(F: np.ndarray, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance (px) of correspondences (N,2) -> (N,2)."""
    x0 = np.c_[uv0, np.ones(len(uv0))]
    x1 = np.c_[uv1, np.ones(len(uv1))]
    Fx0 = x0 @ F.T
    Ftx1 = x1 @ F
    num = np.einsum("ij,ij->i", x1, Fx0)
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    return np.abs(num) / np.sqrt(np.maximum(den, 1e-12))


def triangulate_depths(K: np.ndarray, T_1_0: np.ndarray, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """(N,2) depths (z) in cam 0 and cam 1 of the midpoint triangulation of the two rays."""
    Ki = np.linalg.inv(K)
    r0 = np.c_[uv0, np.ones(len(uv0))] @ Ki.T
    r1 = np.c_[uv1, np.ones(len(uv1))] @ Ki.T @ T_1_0[:3, :3]  # cam-1 rays in cam-0 axes
    c1 = -T_1_0[:3, :3].T @ T_1_0[:3, 3]  # cam-1 centre in cam 0
    # solve a r0 - b r1 = c1 in least squares, per row
    a11 = np.einsum("ij,ij->i", r0, r0)
    a12 = -np.einsum("ij,ij->i", r0, r1)
    a22 = np.einsum("ij,ij->i", r1, r1)
    b1 = r0 @ c1
    b2 = -(r1 @ c1)
    det = a11 * a22 - a12 * a12
    det = np.where(np.abs(det) < 1e-12, np.nan, det)
    a = (b1 * a22 - a12 * b2) / det
    b = (a11 * b2 - a12 * b1) / det
    return np.c_[a, b]  # rays have z = 1 in their own camera: scale = depth


def judge_points(K, T_1_0, uv0, uv1, max_px: float = 2.0) -> np.ndarray:
    """(N,) bool: correspondences consistent with the ground-truth motion."""
    if len(uv0) == 0:
        return np.zeros(0, bool)
    F = fundamental(K, T_1_0)
    z = triangulate_depths(K, T_1_0, uv0, uv1)
    front = np.all(z > 0, axis=1) | ~np.all(np.isfinite(z), axis=1)
    return (sampson(F, uv0, uv1) < max_px) & front


def judge_lines(K, T_1_0, seg0, seg1, min_overlap: float = 0.5, tol_px: float = 3.0):
    """For matched (N,4) segments: (N,) bool right, (N,) bool judgeable (not near the epipolar direction)."""
    F = fundamental(K, T_1_0)
    right = np.zeros(len(seg0), bool)
    judgeable = np.zeros(len(seg0), bool)
    for k, (s0, s1) in enumerate(zip(seg0, seg1)):
        p0, q0 = s0[:2], s0[2:]
        line0 = np.cross(np.r_[p0, 1.0], np.r_[q0, 1.0])
        d0 = (q0 - p0) / np.linalg.norm(q0 - p0)
        ts, ok = [], True
        for e in (s1[:2], s1[2:]):
            l = F.T @ np.r_[e, 1.0]  # epipolar line of e in image 0
            ldir = np.array([l[1], -l[0]]) / np.hypot(l[0], l[1])
            if abs(d0 @ ldir) > np.cos(np.radians(10)):
                ok = False
                break
            x = np.cross(line0, l)
            x = x[:2] / x[2]
            z = triangulate_depths(K, T_1_0, x[None], e[None])[0]
            if not np.all(z > 0):
                ts = None
                break
            ts.append((x - p0) @ d0)
        if not ok:
            continue
        judgeable[k] = True
        if ts is None:
            continue
        L0 = np.linalg.norm(q0 - p0)
        lo, hi = min(ts), max(ts)
        overlap = min(hi, L0 + tol_px) - max(lo, -tol_px)
        right[k] = overlap >= min_overlap * min(L0, max(hi - lo, 1e-9))
    return right, judgeable


def read_kitti_poses(path) -> np.ndarray:
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows
    return T


def read_p0(path) -> np.ndarray:
    with open(path) as f:
        for line in f:
            if line.startswith("P0:"):
                return np.array(line.split()[1:], dtype=float).reshape(3, 4)[:, :3]
    raise ValueError(f"{path}: no P0")


def flow_predicted_segments(prev_kp, cur_kp, pairs, segments, radius: float = 40.0, min_support: int = 3):
    """(M,4) previous segments moved by the median flow of point matches near their midpoints (NaN: too few).

    A stand-in for the tracker's prediction (landmarks projected with the constant-velocity pose) where no 3D
    map exists: it uses only the matcher's own point matches, no ground truth.
    """
    out = np.full((len(segments), 4), np.nan)
    if len(pairs) == 0:
        return out
    p0 = prev_kp[pairs[:, 0]]
    flow = cur_kp[pairs[:, 1]] - p0
    mid = (segments[:, :2] + segments[:, 2:]) / 2
    for k, m in enumerate(mid):
        near = np.linalg.norm(p0 - m, axis=1) < radius
        if near.sum() >= min_support:
            f = np.median(flow[near], axis=0)
            out[k] = segments[k] + np.r_[f, f]
    return out


def project_visible_edges(edges_w, T_world_cam, K, depth, min_len_px: float = 50.0, step_px: float = 2.0):
    """Visible parts of (E,2,3) world edges in a camera: list of (S,2) visible sample pixels per edge, for edges
    whose visible part spans >= min_len_px. Visibility: in the image, in front, and not behind the depth map
    (nearest depth in a 3x3 block, 2 % + 5 cm tolerance)."""
    import cv2

    h, w = depth.shape
    T = np.linalg.inv(T_world_cam)
    e = edges_w @ T[:3, :3].T + T[:3, 3]  # (E,2,3) in the camera
    a, b = e[:, 0], e[:, 1]
    near = 0.3
    keep = (a[:, 2] > near) | (b[:, 2] > near)
    a, b = a[keep], b[keep]
    # clip to z > near
    dz = np.where(np.abs(b[:, 2] - a[:, 2]) < 1e-12, 1e-12, b[:, 2] - a[:, 2])
    ta = np.where(a[:, 2] < near, (near - a[:, 2]) / dz, 0.0)
    tb = np.where(b[:, 2] < near, (b[:, 2] - near) / dz, 0.0)
    a, b = a + ta[:, None] * (b - a), b - tb[:, None] * (b - a)
    pa = a @ K.T
    pb = b @ K.T
    ua, ub = pa[:, :2] / pa[:, 2:], pb[:, :2] / pb[:, 2:]
    lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
    on = (hi[:, 0] >= 0) & (lo[:, 0] < w) & (hi[:, 1] >= 0) & (lo[:, 1] < h)
    on &= np.linalg.norm(ua - ub, axis=1) >= min_len_px
    zmin = cv2.erode(np.where(np.isfinite(depth), depth, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
    out = []
    for A, B in zip(a[on], b[on]):
        n = int(np.ceil(np.linalg.norm((A @ K.T)[:2] / A[2] - (B @ K.T)[:2] / B[2]) / step_px)) + 1
        s = np.linspace(0, 1, n)[:, None]
        X = A + s * (B - A)
        uv = (X @ K.T)[:, :2] / X[:, 2:]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if inside.sum() < 2:
            continue
        uv, z = uv[inside], X[inside, 2]
        d = zmin[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
        vis = d >= z - (0.02 * z + 0.05)
        if vis.sum() >= 2 and np.linalg.norm(uv[vis][0] - uv[vis][-1]) >= min_len_px:
            out.append(uv[vis])
    return out


def point_segment_distance(p: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """(P,S) distances of points (P,2) to segments (S,4)."""
    a, b = seg[None, :, :2], seg[None, :, 2:]
    d = b - a
    t = np.clip(np.einsum("psk,psk->ps", p[:, None, :] - a, d) / np.maximum(np.einsum("psk,psk->ps", d, d), 1e-12),
                0, 1)
    q = a + t[..., None] * d
    return np.linalg.norm(p[:, None, :] - q, axis=2)


def edge_precision_recall(segments, visible, tol_px: float = 2.0, cover: float = 0.5, angle_deg: float = 3.0):
    """Precision: share of segments whose 5 sample points each lie within tol of a visible true edge (the chord
    of its visible samples) parallel to the segment within angle_deg; true edges split into collinear pieces
    count as one line. Recall: share of visible true edges whose samples are covered (within tol of some
    parallel segment) for at least `cover` of their samples."""
    if len(visible) == 0:
        return np.nan, np.nan
    chords = np.array([np.r_[v[0], v[-1]] for v in visible])
    if len(segments) == 0:
        return np.nan, 0.0
    def angles(s):
        return np.arctan2(s[:, 3] - s[:, 1], s[:, 2] - s[:, 0]) % np.pi
    dth = np.abs(angles(segments)[:, None] - angles(chords)[None, :])
    parallel = np.minimum(dth, np.pi - dth) < np.radians(angle_deg)  # (M,V)
    s = np.linspace(0, 1, 5)
    pts = segments[:, None, :2] + s[None, :, None] * (segments[:, None, 2:] - segments[:, None, :2])
    d = point_segment_distance(pts.reshape(-1, 2), chords).reshape(len(segments), 5, len(chords))
    near = (d < tol_px) & parallel[:, None, :]
    on_edge = np.all(np.any(near, axis=2), axis=1)
    found = 0
    for k, v in enumerate(visible):
        cand = parallel[:, k]
        if cand.any():
            dv = point_segment_distance(v, segments[cand])
            found += np.mean(dv.min(axis=1) < tol_px) >= cover
    return float(on_edge.mean()), found / len(visible)


def edge_ids_of_segments(segments, visible, tol_px: float = 2.0, angle_deg: float = 3.0) -> np.ndarray:
    """(M,) index into `visible` of the true edge each segment lies on (its 5 samples within tol of that edge's
    chord, parallel within angle_deg), -1 where none."""
    out = np.full(len(segments), -1)
    if len(visible) == 0 or len(segments) == 0:
        return out
    chords = np.array([np.r_[v[0], v[-1]] for v in visible])
    ang = lambda s: np.arctan2(s[:, 3] - s[:, 1], s[:, 2] - s[:, 0]) % np.pi  # noqa: E731
    dth = np.abs(ang(segments)[:, None] - ang(chords)[None, :])
    parallel = np.minimum(dth, np.pi - dth) < np.radians(angle_deg)
    s = np.linspace(0, 1, 5)
    pts = segments[:, None, :2] + s[None, :, None] * (segments[:, None, 2:] - segments[:, None, :2])
    d = point_segment_distance(pts.reshape(-1, 2), chords).reshape(len(segments), 5, len(chords))
    worst = np.where(parallel, d.max(axis=1), np.inf)
    best = worst.argmin(axis=1)
    ok = worst[np.arange(len(segments)), best] < tol_px
    out[ok] = best[ok]
    return out
