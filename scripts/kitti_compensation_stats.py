"""KITTI's motion compensation measured on its scans: how a scan is stored, whether a ring holds more than one turn,
how much of the sweep's motion the compensation removed, and to which instant.

For each source (real KITTI odometry scans, a raw drive's sweeps, or a twin of either), over its frames:
  layout      storage order (each ring a turn of increasing azimuth from facing forward: KITTI's files; of decreasing
              azimuth from behind: the twins'), rings found in storage order (runs), returns per ring, median azimuth
              step, rings' azimuth span, each full ring's densest 10 deg sector against its median one (an overlap
              would show as runs past the 64 beams or as a sector of about twice the returns; plvo.lidar.seam)
  seam        on the ground behind the car, one ring's returns at the sweep's end minus those at its start, along x
              (plvo.lidar.seam.seam_ground_split): the motion the compensation removed over the sweep (0: a raw
              sweep), against the truth's motion over the sweep (speed times the sweep's duration); the residual is
              what the compensation left. Fitted against whole records of the GPS/INS clock (--record-s, KITTI's
              100 Hz; a twin's from its scene.json): the records nearest the sweep's start and end span 10 or 11
              periods of a 0.1041 s sweep, and the sign of each frame's residual is compared with that prediction
  icp         consecutive scans registered point-to-plane (open3d, from the truth's motion): the registration's yaw and
              forward step against the truth's, their spread, and how the yaw follows the seam residual
  camera      the reference instant: the lidar's depth edges projected into cam0 with the lidar taken at the frame's
              time + tau (the truth interpolated), scored by the image's gradient there; the tau of the best score
              (a parabola through the mean normalised scores). A raw drive's returns are moved by their own azimuth
              times first: clockwise (as plvo reads them), counter-clockwise, or not at all, each scored
  reskew      (--reskew, odometry layout) consecutive scans 5 frames apart registered after a further deskew by a
              share alpha of the truth's motion: the alpha of the least residual (0 for a scan compensated right)

Usage: python scripts/kitti_compensation_stats.py OUT_DIR NAME=KIND:ROOT:SEQ [NAME=KIND:ROOT:SEQ ...]
           [--frames A:B] [--record-s 0.01] [--reskew]
  KIND odometry (ROOT/sequences/SEQ, poses/SEQ.txt: real KITTI or a twin) or raw (ROOT/DATE/DATE_drive_NNNN_sync)
  e.g. real04=odometry:../shared/data/kitti:04 raw0009=raw:../shared/data/kitti_raw:2011_09_26_drive_0009
Writes OUT_DIR/compensation_stats.json and compensation_stats.md.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from plvo.data.kitti import KittiOdometry, KittiRaw
from plvo.lidar.deskew import azimuth_times, deskew, twist_from_motion
from plvo.lidar.scan import raise_elevation
from plvo.lidar.seam import ring_turns, seam_ground_split

TAUS_S = np.arange(-0.015, 0.0101, 0.001)
ALPHAS = (-2.0, -1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0)
MIN_SEAM_RINGS = 5


@dataclass
class Source:
    name: str
    kind: str
    ds: object
    scans: list
    gt: np.ndarray  # (N,4,4) T_world_cam0 at the frames' times
    times: np.ndarray
    T_cam_velo: np.ndarray
    sweep_s: np.ndarray  # (N,) each sweep's duration
    record_s: float | None  # the GPS/INS record period in the source's clock (None: no record model)


def load(spec: str, frames: tuple[int, int] | None, record_s: float) -> Source:
    name, rest = spec.split("=", 1)
    kind, root, seq = rest.split(":", 2)
    sel = None if frames is None else slice(frames[0], frames[1])
    if kind == "odometry":
        ds = KittiOdometry(root, seq, sel)
        times = ds.times
        scene = Path(root) / "sequences" / seq / "gt" / "scene.json"
        sweep = np.full(len(ds), float(np.median(np.diff(times))))
        if scene.is_file():  # a twin: its clock runs 0.1 s a sweep; its records as its realism set them
            effects = json.loads(scene.read_text()).get("realism", {}).get("lidar_effects") or {}
            n = float(effects.get("compensation_records_a_sweep", 0.0))
            record_s = sweep[0] / n if n > 0 else None
    elif kind == "raw":
        ds = KittiRaw(root, seq, sel)
        times = ds.times
        sweep = np.asarray(ds._sweep_s, np.float64)
    else:
        raise SystemExit(f"{spec}: KIND is odometry or raw")
    gt = ds.gt_T_world_cam
    if gt is None:
        raise SystemExit(f"{spec}: no ground truth")
    scans = [ds.load_scan(i) for i in range(len(ds))]
    return Source(name, kind, ds, scans, gt, times, ds.calib.T_cam_velo, sweep, record_s)


def pose_at(src: Source, t: np.ndarray) -> np.ndarray:
    """(K,) times -> (K,4,4) T_world_velo, the truth interpolated (linear, extrapolated past the ends)."""
    t = np.atleast_1d(t)
    i = np.clip(np.searchsorted(src.times, t) - 1, 0, len(src.times) - 2)
    a = (t - src.times[i]) / (src.times[i + 1] - src.times[i])
    out = np.tile(np.eye(4), (len(t), 1, 1))
    for k in range(len(t)):
        A, B = src.gt[i[k]], src.gt[i[k] + 1]
        step = Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).as_rotvec()
        out[k, :3, :3] = A[:3, :3] @ Rotation.from_rotvec(a[k] * step).as_matrix()
        out[k, :3, 3] = (1 - a[k]) * A[:3, 3] + a[k] * B[:3, 3]
    return out @ src.T_cam_velo


def layout(src: Source) -> dict:
    turns = [ring_turns(s) for s in src.scans]
    returns = np.concatenate([t.returns for t in turns])
    steps = np.concatenate([t.step_deg for t in turns])
    densest = np.concatenate([t.densest for t in turns])
    full = returns >= 0.9 * returns.max()  # the rings that return (nearly) every firing
    az = np.arctan2(src.scans[0][:, 1], src.scans[0][:, 0])
    increasing = np.median(np.angle(np.exp(1j * np.diff(az)))) > 0
    runs = [len(t.returns) for t in turns]
    return {"order": "each ring counter-clockwise (increasing azimuth)" if increasing else
            "each ring clockwise (decreasing azimuth)", "first_return_azimuth_deg": round(float(np.degrees(az[0])), 2),
            "rings_min": int(min(runs)), "rings_max": int(max(runs)),
            "returns_per_ring_max": int(returns.max()),
            "median_step_deg": round(float(np.median(steps)), 4),
            "mean_step_deg_fullest_ring": round(360.0 / float(returns.max()), 4),
            "span_deg_max": round(float(max(t.span_deg.max() for t in turns)), 3),
            "densest_sector_median": round(float(np.median(densest[full])), 3),
            "densest_sector_max": round(float(densest[full].max()), 3),
            "turn_at_median_step_deg": round(float(returns.max() * np.median(steps)), 1)}


def seam(src: Source) -> dict:
    rows = []
    for i in range(1, len(src.scans) - 1):
        split = seam_ground_split(src.scans[i])
        if len(split) < MIN_SEAM_RINGS:
            continue
        half = 0.5 * src.sweep_s[i]
        T0, T, T1 = pose_at(src, np.array([src.times[i] - half, src.times[i], src.times[i] + half]))
        motion = (np.linalg.inv(T) @ np.append(T1[:3, 3], 1.0))[0] - (np.linalg.inv(T) @ np.append(T0[:3, 3], 1.0))[0]
        rows.append((i, float(np.median(split)), float(motion), len(split)))
    if not rows:
        return {"frames": 0}
    R = np.array(rows)
    resid = R[:, 1] - R[:, 2]
    out = {"frames": len(R), "rings_a_frame": float(np.median(R[:, 3])),
           "removed_m_median": round(float(np.median(R[:, 1])), 4),
           "truth_motion_m_median": round(float(np.median(R[:, 2])), 4),
           "removed_over_truth_median": round(float(np.median(R[:, 1] / R[:, 2])), 4),
           "residual_m_median": round(float(np.median(resid)), 4),
           "residual_m_abs_median": round(float(np.median(np.abs(resid))), 4),
           "residual_m_sd": round(float(np.std(resid)), 4),
           "per_frame": [[int(f), round(a, 4), round(b, 4)] for f, a, b, _ in rows]}
    if src.record_s and np.median(R[:, 1] / R[:, 2]) > 0.5:  # a compensated scan: its records can be fitted
        out["records"] = record_fit(src, R, resid)
    return out


def record_fit(src: Source, R: np.ndarray, resid: np.ndarray) -> dict:
    """The phase of the record clock that best predicts each frame's residual sign from whole records nearest the
    sweep's start and end; the frames of each record count, their removed span (s) and residual (m)."""
    f = R[:, 0].astype(int)
    c = float(src.record_s)  # type: ignore[arg-type]
    start = (src.times[f] - 0.5 * src.sweep_s[f]) / c
    full = src.sweep_s[f] / c
    best = (-1.0, 0.0)
    for phase in np.arange(0.0, 1.0, 0.005):
        n = np.floor(start + full + phase + 0.5) - np.floor(start + phase + 0.5)
        agree = float(np.mean((n > full) == (resid > 0)))
        best = max(best, (agree, phase))
    n = np.floor(start + full + best[1] + 0.5) - np.floor(start + best[1] + 0.5)
    speed = R[:, 2] / src.sweep_s[f]
    groups = {}
    for k in np.unique(n):
        m = n == k
        groups[f"{int(k)}"] = {"frames": int(m.sum()), "removed_span_s": round(float(np.median(R[m, 1] / speed[m])), 5),
                               "records_span_s": round(float(k * c), 5),
                               "residual_m_median": round(float(np.median(resid[m])), 4)}
    return {"record_s": c, "sweep_in_records": round(float(np.median(full)), 3), "sign_agreement": round(best[0], 4),
            "by_records": groups}


def icp(src: Source, seam_rows: dict) -> dict:
    import open3d as o3d

    def cloud(i):
        s = raise_elevation(src.scans[i], src.ds.calib.lidar_elevation_offset_deg)[:, :3].astype(np.float64)
        r = np.linalg.norm(s, axis=1)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s[(r > 3) & (r < 60)])).voxel_down_sample(0.3)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(1.0, 20))
        return pc

    Tv = src.gt @ src.T_cam_velo
    rows = []
    prev = cloud(0)
    for i in range(1, len(src.scans)):
        cur = cloud(i)
        init = np.linalg.inv(Tv[i - 1]) @ Tv[i]
        fit = o3d.pipelines.registration.registration_icp(
            cur, prev, 0.5, init, o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
        d = np.linalg.inv(init) @ fit.transformation
        rows.append((i, float(d[0, 3]), float(np.degrees(np.arctan2(d[1, 0], d[0, 0])))))
        prev = cur
    R = np.array(rows)
    out = {"pairs": len(R), "forward_step_m_median": round(float(np.median(R[:, 1])), 4),
           "forward_step_m_sd": round(float(np.std(R[:, 1])), 4),
           "yaw_deg_median": round(float(np.median(R[:, 2])), 5), "yaw_deg_sd": round(float(np.std(R[:, 2])), 5)}
    resid = {f: a - b for f, a, b in seam_rows.get("per_frame", [])}
    both = [(y, resid[f] - resid[f - 1]) for f, _, y in rows if f in resid and f - 1 in resid]
    if len(both) > 5:
        y, dr = np.array(both).T
        out["yaw_vs_residual_step_corr"] = round(float(np.corrcoef(y, dr)[0, 1]), 3)
        out["yaw_deg_per_m_residual_step"] = round(float(np.polyfit(dr, y, 1)[0]), 4)
    return out


def depth_edges(scan: np.ndarray) -> np.ndarray:
    """Indices of the nearer return at each range jump between neighbours in storage order (> 0.5 m and 10 %)."""
    r = np.linalg.norm(scan[:, :3], axis=1)
    dr = np.diff(r)
    jump = np.abs(dr) > np.maximum(0.5, 0.1 * np.minimum(r[1:], r[:-1]))
    k = np.flatnonzero(jump)
    return np.unique(np.where(dr[k] > 0, k, k + 1))


def camera(src: Source, timing: str | None) -> dict:
    """The reference instant from the image: tau of the best edge score (timing: each return moved by its own
    azimuth time first, "clockwise" or "counter-clockwise", or None: the scan as stored)."""
    K = src.ds.calib.K
    scores = []
    for i in range(len(src.scans)):
        frame = src.ds[i]
        s = raise_elevation(src.scans[i], frame.calib.lidar_elevation_offset_deg).astype(np.float64)
        P = s[depth_edges(s), :3]
        P = P[(P[:, 0] > 2.0) & (np.linalg.norm(P, axis=1) < 40.0)]
        if timing is not None:
            j = min(i, len(src.times) - 2)
            twist = twist_from_motion(np.linalg.inv(src.gt[j]) @ src.gt[j + 1], src.times[j + 1] - src.times[j],
                                      src.T_cam_velo)
            sign = 1.0 if timing == "clockwise" else -1.0
            P = deskew(P, sign * azimuth_times(P, float(src.sweep_s[i])), twist)
        g = frame.image.astype(np.float32)
        grad = cv2.GaussianBlur(np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)), (0, 0), 2.0)
        row = []
        for Q in np.linalg.inv(src.gt[i])[None] @ pose_at(src, src.times[i] + TAUS_S):
            X = P @ Q[:3, :3].T + Q[:3, 3]
            front = X[:, 2] > 1.0
            u = K[0, 0] * X[front, 0] / X[front, 2] + K[0, 2]
            v = K[1, 1] * X[front, 1] / X[front, 2] + K[1, 2]
            inb = (u >= 0) & (u < g.shape[1] - 1) & (v >= 0) & (v < g.shape[0] - 1)
            row.append(float(grad[v[inb].astype(int), u[inb].astype(int)].mean()) if inb.any() else np.nan)
        scores.append(row)
    S = np.array(scores)
    m = np.nanmean(S / np.nanmean(S, axis=1, keepdims=True), axis=0)
    c = np.polyfit(TAUS_S, m, 2)
    best = float(-c[1] / (2 * c[0]))
    return {"timing": timing or "as stored", "tau_s_best": round(best, 5),
            "score_at_best": round(float(np.polyval(c, best)), 4),
            "score_at_0": round(float(m[np.argmin(np.abs(TAUS_S))]), 4)}


def reskew(src: Source, gap: int = 5) -> dict:
    """Mean inlier rms of scans `gap` frames apart registered after a further deskew by alpha of the truth's
    motion, for each alpha of ALPHAS."""
    import open3d as o3d

    Tv = src.gt @ src.T_cam_velo

    def cloud(i, alpha):
        s = raise_elevation(src.scans[i], src.ds.calib.lidar_elevation_offset_deg)[:, :3].astype(np.float64)
        j = min(i, len(src.times) - 2)
        twist = twist_from_motion(np.linalg.inv(src.gt[j]) @ src.gt[j + 1], src.times[j + 1] - src.times[j],
                                  src.T_cam_velo)
        s = deskew(s, azimuth_times(s, float(src.sweep_s[i])), alpha * twist)
        r = np.linalg.norm(s, axis=1)
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s[(r > 3) & (r < 50)])).voxel_down_sample(0.2)

    out = {}
    for alpha in ALPHAS:
        rms = []
        for i in range(0, len(src.scans) - gap, 3):
            a, b = cloud(i, alpha), cloud(i + gap, alpha)
            a.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(1.0, 20))
            fit = o3d.pipelines.registration.registration_icp(
                b, a, 0.3, np.linalg.inv(Tv[i]) @ Tv[i + gap],
                o3d.pipelines.registration.TransformationEstimationPointToPlane(),
                o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=40))
            rms.append(fit.inlier_rmse)
        out[f"{alpha:g}"] = round(float(np.mean(rms)), 5)
    out["best_alpha"] = float(min(ALPHAS, key=lambda a: out[f"{a:g}"]))
    return out


def report(results: dict) -> list[str]:
    lines = ["| source | order | first az deg | rings (runs) | returns/ring max | median step deg | "
             "360 / max returns | max span deg | densest 10 deg sector / median (median, max) | "
             "turn at median step deg |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |"]
    for name, r in results.items():
        L = r["layout"]
        rings = str(L["rings_min"]) if L["rings_min"] == L["rings_max"] else f"{L['rings_min']}-{L['rings_max']}"
        lines.append(f"| {name} | {L['order']} | {L['first_return_azimuth_deg']} | {rings} | "
                     f"{L['returns_per_ring_max']} | {L['median_step_deg']} | {L['mean_step_deg_fullest_ring']} | "
                     f"{L['span_deg_max']} | {L['densest_sector_median']}, {L['densest_sector_max']} | "
                     f"{L['turn_at_median_step_deg']} |")
    lines += ["", "| source | frames | removed over the sweep m | truth's motion m | removed / truth | residual m "
              "(median, median abs, sd) | record fit: agreement, by records (frames, removed span s, residual m) |",
              "| --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for name, r in results.items():
        S = r["seam"]
        if not S.get("frames"):
            lines.append(f"| {name} | 0 | - | - | - | - | - |")
            continue
        rec = S.get("records")
        fit = "-" if rec is None else f"{rec['sign_agreement']:.2f}; " + "; ".join(
            f"{k}: {g['frames']}, {g['removed_span_s']}, {g['residual_m_median']:+.3f}"
            for k, g in rec["by_records"].items())
        lines.append(f"| {name} | {S['frames']} | {S['removed_m_median']} | {S['truth_motion_m_median']} | "
                     f"{S['removed_over_truth_median']} | {S['residual_m_median']:+.4f}, {S['residual_m_abs_median']}"
                     f", {S['residual_m_sd']} | {fit} |")
    lines += ["", "| source | ICP pairs | forward step - truth m (median, sd) | yaw - truth deg (median, sd) | "
              "yaw vs residual step (corr, deg/m) | camera: tau s (score at tau, at 0) | reskew best alpha |",
              "| --- | ---: | --- | --- | --- | --- | ---: |"]
    for name, r in results.items():
        C = r["icp"]
        corr = f"{C['yaw_vs_residual_step_corr']}, {C['yaw_deg_per_m_residual_step']}" \
            if "yaw_vs_residual_step_corr" in C else "-"
        cams = "; ".join(f"{c['timing']}: {c['tau_s_best']:+.4f} ({c['score_at_best']}, {c['score_at_0']})"
                         for c in r["camera"])
        rs = r.get("reskew", {}).get("best_alpha", "-")
        lines.append(f"| {name} | {C['pairs']} | {C['forward_step_m_median']:+.4f}, {C['forward_step_m_sd']} | "
                     f"{C['yaw_deg_median']:+.5f}, {C['yaw_deg_sd']} | {corr} | {cams} | {rs} |")
    return lines


def main(argv: list[str]) -> int:
    frames, record_s, do_reskew = None, 0.01, False
    if "--frames" in argv:
        k = argv.index("--frames")
        a, b = argv[k + 1].split(":")
        frames = (int(a), int(b))
        argv = argv[:k] + argv[k + 2:]
    if "--record-s" in argv:
        k = argv.index("--record-s")
        record_s = float(argv[k + 1])
        argv = argv[:k] + argv[k + 2:]
    if "--reskew" in argv:
        do_reskew = True
        argv.remove("--reskew")
    if len(argv) < 2:
        print(__doc__)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for spec in argv[1:]:
        src = load(spec, frames, record_s)
        r = {"layout": layout(src), "seam": seam(src)}
        r["icp"] = icp(src, r["seam"])
        timings = [None] if src.kind == "odometry" and src.ds.scans_compensated else \
            [None, "clockwise", "counter-clockwise"]
        r["camera"] = [camera(src, t) for t in timings]
        if do_reskew and src.kind == "odometry":
            r["reskew"] = reskew(src)
        results[src.name] = r
        print(f"{src.name}: done", file=sys.stderr)
    (out / "compensation_stats.json").write_text(json.dumps(results, indent=1))
    lines = report(results)
    (out / "compensation_stats.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
