"""Lidar scan -> image: projection through T_cam_velo and K, a per-pixel z-buffer, and a cell grid index.

The grid index is a CSR structure: projected points sorted by cell id (row-major cells of `cell_px` pixels) and
`cell_start[c] .. cell_start[c+1]` the points of cell c. The cells of one grid row are contiguous, so the points in
any pixel rectangle are a few contiguous runs (one per cell row) and a batch of patch queries is answered with
vectorised run expansion, no Python loop over features.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from plvo.errors import PlvoError
from plvo.types import Calibration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ProjectedScan:
    """Scan points visible in the image after the z-buffer, sorted by grid cell.

    uv: (P,2) pixels; depth: (P,) z in the camera frame (m); pts_cam: (P,3) camera-frame points;
    scan_index: (P,) row of each point in the input scan; cell_start: (n_cells+1,) CSR offsets into the sorted
    arrays; cell_px: grid cell size (px); n_cols, n_rows: grid size in cells; width, height: image size (px).
    """

    uv: np.ndarray
    depth: np.ndarray
    pts_cam: np.ndarray
    scan_index: np.ndarray
    cell_start: np.ndarray
    cell_px: int
    n_cols: int
    n_rows: int
    width: int
    height: int

    def __len__(self) -> int:
        return int(len(self.depth))


def project_scan(
    scan: np.ndarray,
    calib: Calibration,
    min_depth: float = 0.5,
    max_depth: float = 120.0,
    cell_px: int = 8,
    zbuffer_px: int = 1,
) -> ProjectedScan:
    """(N,4) or (N,3) lidar-frame scan -> ProjectedScan (camera frame, pixels), nearest point per zbuffer block."""
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[1] < 3:
        raise PlvoError(f"project_scan: field 'scan' must be (N,3) or (N,4), got {scan.shape}")
    xyz = np.ascontiguousarray(scan[:, :3], dtype=np.float32)
    if not np.all(np.isfinite(xyz)):
        raise PlvoError("project_scan: field 'scan' contains NaN or inf coordinates")
    zb = max(int(zbuffer_px), 1)
    if cell_px % zb:
        raise PlvoError(f"project_scan: cell_px {cell_px} must be a multiple of zbuffer_px {zb}")
    T = np.asarray(calib.T_cam_velo, dtype=float)
    # Matrix-vector products, not (N,3)@(3,3): OpenBLAS's threaded GEMM on tall thin arrays took 30-45 ms for
    # 120k points on a loaded 2-core machine, GEMV under 1 ms. float32 is far below lidar noise.
    R32 = np.ascontiguousarray(T[:3, :3], dtype=np.float32)
    z_all = xyz @ R32[2] + np.float32(T[2, 3])
    keep = np.flatnonzero((z_all > min_depth) & (z_all < max_depth))
    xk = xyz[keep]
    pts = np.stack([xk @ R32[0], xk @ R32[1], z_all[keep] - np.float32(T[2, 3])], axis=1).astype(np.float64)
    pts += T[:3, 3]
    z = pts[:, 2]
    K = calib.K
    u = K[0, 0] * pts[:, 0] / z + K[0, 2]
    v = K[1, 1] * pts[:, 1] / z + K[1, 2]
    W, H = int(calib.width), int(calib.height)
    inside = np.flatnonzero((u >= 0) & (v >= 0) & (u < W) & (v < H))
    keep, pts, z, u, v = keep[inside], pts[inside], z[inside], u[inside], v[inside]
    n_cols, n_rows = -(-W // cell_px), -(-H // cell_px)
    ui, vi = u.astype(np.int64), v.astype(np.int64)
    cell = (vi // cell_px) * n_cols + ui // cell_px
    per = cell_px // zb
    block = cell * (per * per) + ((vi % cell_px) // zb) * per + (ui % cell_px) // zb
    # One sort serves the z-buffer (nearest first within a block) and the grid (blocks grouped by cell).
    key = (block << 24) + np.minimum(z * 1e4, 2**24 - 1).astype(np.int64)
    order = np.argsort(key)
    bs = block[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = bs[1:] != bs[:-1]
    sel = order[first]
    counts = np.bincount(cell[sel], minlength=n_cols * n_rows)
    cell_start = np.zeros(n_cols * n_rows + 1, dtype=np.int64)
    np.cumsum(counts, out=cell_start[1:])
    return ProjectedScan(
        uv=np.stack([u[sel], v[sel]], axis=1),
        depth=z[sel],
        pts_cam=pts[sel],
        scan_index=keep[sel],
        cell_start=cell_start,
        cell_px=int(cell_px),
        n_cols=int(n_cols),
        n_rows=int(n_rows),
        width=W,
        height=H,
    )


def expand_runs(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(R,) run starts and (R,) lengths -> (sum lengths,) concatenated aranges, vectorised."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    nz = lengths > 0
    starts, lengths = np.asarray(starts, dtype=np.int64)[nz], lengths[nz]
    ends = np.cumsum(lengths)
    out = np.ones(total, dtype=np.int64)
    out[0] = starts[0]
    # At each run boundary jump from the previous run's last index to the next run's start.
    out[ends[:-1]] = starts[1:] - (starts[:-1] + lengths[:-1] - 1)
    return np.cumsum(out)


def query_boxes(proj: ProjectedScan, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q,4) pixel boxes u0,v0,u1,v1 (inclusive) -> (owner (K,), point index (K,)) of projected points inside.

    Owners come out sorted ascending; point indices index the ProjectedScan arrays.
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    cp = proj.cell_px
    c0 = np.clip(np.floor(boxes[:, 0] / cp).astype(np.int64), 0, proj.n_cols - 1)
    c1 = np.clip(np.floor(boxes[:, 2] / cp).astype(np.int64), 0, proj.n_cols - 1)
    r0 = np.clip(np.floor(boxes[:, 1] / cp).astype(np.int64), 0, proj.n_rows - 1)
    r1 = np.clip(np.floor(boxes[:, 3] / cp).astype(np.int64), 0, proj.n_rows - 1)
    n_rows_q = np.maximum(r1 - r0 + 1, 0)
    owner_run = np.repeat(np.arange(len(boxes)), n_rows_q)
    row = expand_runs(r0, n_rows_q)
    run_start = proj.cell_start[row * proj.n_cols + c0[owner_run]]
    run_end = proj.cell_start[row * proj.n_cols + c1[owner_run] + 1]
    lengths = run_end - run_start
    idx = expand_runs(run_start, lengths)
    owner = np.repeat(owner_run, lengths)
    uv = proj.uv[idx]
    b = boxes[owner]
    inside = (uv[:, 0] >= b[:, 0]) & (uv[:, 0] <= b[:, 2]) & (uv[:, 1] >= b[:, 1]) & (uv[:, 1] <= b[:, 3])
    return owner[inside], idx[inside]


def query_patches(proj: ProjectedScan, centers: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """(Q,2) pixel centres and patch half-size (px) -> (owner (K,), point index (K,)), owners ascending."""
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    return query_boxes(proj, np.concatenate([c - half, c + half], axis=1))


def to_padded(owner: np.ndarray, idx: np.ndarray, n_queries: int, max_per: int | None = None):
    """Sorted (K,) owners and (K,) indices -> (index (Q,P) int with -1 padding, count (Q,)); P = max count (capped)."""
    counts = np.bincount(owner, minlength=n_queries).astype(np.int64)
    P = int(counts.max()) if len(counts) and counts.size else 0
    if max_per is not None:
        P = min(P, int(max_per))
    out = np.full((n_queries, max(P, 1)), -1, dtype=np.int64)
    if len(owner):
        starts = np.zeros(n_queries, dtype=np.int64)
        np.cumsum(counts[:-1], out=starts[1:])
        rank = np.arange(len(owner)) - starts[owner]
        ok = rank < P
        out[owner[ok], rank[ok]] = idx[ok]
    return out, np.minimum(counts, max(P, 0))


def query_segments(
    proj: ProjectedScan, segments: np.ndarray, half_width: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(M,4) segments, band half-width (px) -> owner (K,), point index (K,), t (K,) in [0,1], distance (K,) px.

    The band is the points within half_width of the segment's supporting line whose foot lies on the segment.
    Owners come out sorted ascending.
    """
    seg = np.asarray(segments, dtype=float).reshape(-1, 4)
    a, b = seg[:, :2], seg[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    cp = proj.cell_px
    # Sample each segment every half cell; the cells around each sample cover the whole band.
    n_samp = np.ceil(length / (0.5 * cp)).astype(np.int64) + 1
    owner_s = np.repeat(np.arange(len(seg)), n_samp)
    first = np.repeat(np.cumsum(n_samp) - n_samp, n_samp)
    s = (np.arange(len(owner_s)) - first) / np.maximum(n_samp[owner_s] - 1, 1)
    xy = a[owner_s] + s[:, None] * (b - a)[owner_s]
    # Offsets on the cell lattice: every cell meeting [x - hw - cp/4, x + hw + cp/4] holds one of these points.
    n_off = int(np.ceil((half_width + 0.25 * cp) / cp))
    offsets = np.arange(-n_off, n_off + 1) * float(cp)
    keys = []
    for dx in offsets:
        for dy in offsets:
            cx = np.clip(np.floor((xy[:, 0] + dx) / cp).astype(np.int64), 0, proj.n_cols - 1)
            cy = np.clip(np.floor((xy[:, 1] + dy) / cp).astype(np.int64), 0, proj.n_rows - 1)
            keys.append(owner_s * (proj.n_cols * proj.n_rows) + cy * proj.n_cols + cx)
    keys = np.unique(np.concatenate(keys))
    n_cells = proj.n_cols * proj.n_rows
    owner_c, cell = keys // n_cells, keys % n_cells
    starts = proj.cell_start[cell]
    lengths = proj.cell_start[cell + 1] - starts
    idx = expand_runs(starts, lengths)
    owner = np.repeat(owner_c, lengths)
    d = (b - a)[owner] / np.maximum(length[owner], 1e-9)[:, None]
    rel = proj.uv[idx] - a[owner]
    t = np.einsum("ki,ki->k", rel, d) / np.maximum(length[owner], 1e-9)
    perp = np.abs(rel[:, 0] * d[:, 1] - rel[:, 1] * d[:, 0])
    ok = (perp <= half_width) & (t >= 0.0) & (t <= 1.0)
    return owner[ok], idx[ok], t[ok], perp[ok]
