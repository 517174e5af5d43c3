"""KITTI twins: a 20-frame twin of KITTI 07 (frames 60:80, realistic sensors) reproduces the followed poses, its lidar
returns (motion-compensated sweep, movers included), taken back through the lidar's recorded imperfections, land on
camera pixels of their own depth, its movers are where their boxes say in both sensors, its scenery does not depend
on the driving direction, and KISS-ICP tracks it."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from plvo.data.kitti import KittiOdometry
from plvo.data.trajectory import read_kitti_poses
from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.twin.follow import load_followed
from plvo_synth.twin.layout import Layout
from plvo_synth.twin.lidars import LIDAR_MODELS, point_times, sweep_time
from plvo_synth.twin.scenery import build_world

SEQ = "07"
FIRST, N = 60, 20  # conftest.TWIN_FRAMES
TOL_M, TOL_REL = 0.06, 0.004  # range noise 1-2 cm (1 sigma) plus the float32 caster


def _seq(root):
    return root / "sequences" / SEQ


def _frame_data(root, i):
    seq = _seq(root)
    scan = np.fromfile(seq / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)
    labels = np.load(seq / "gt" / "lidar_movers" / f"{i:06d}.npy")
    depth = np.load(seq / "gt" / "depth" / f"{i:06d}.npy")
    ids = cv2.imread(str(seq / "gt" / "movers" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
    boxes = [json.loads(line) for line in (seq / "gt" / "boxes.jsonl").read_text().splitlines()][i]
    return scan, labels, depth, ids, boxes


def _interp_poses(T: np.ndarray, times: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Poses (K,4,4) at times (K,) -> poses at `at` (linear position, slerp rotation; clamped at the ends)."""
    at = np.clip(at, times[0], times[-1])
    out = np.tile(np.eye(4), (len(at), 1, 1))
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(T[:, :3, :3]))(at).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(at, times, T[:, k, 3])
    return out


def _ego_at(gt: np.ndarray, i: int, dt: np.ndarray) -> np.ndarray:
    """T_world_cam at frame i's time + dt (s), from the poses file (10 Hz)."""
    lo, hi = max(i - 1, 0), min(i + 2, len(gt))
    times = np.arange(lo, hi) * sensors.FRAME_DT
    t = i * sensors.FRAME_DT + dt
    T = _interp_poses(gt[lo:hi], times, t)
    # the first and last frames extrapolate their end step (as the generator does)
    for end, nb in ((0, 1), (len(gt) - 1, len(gt) - 2)):
        if i == end:
            outside = (t < 0) if end == 0 else (t > times[-1])
            w = (t[outside] - end * sensors.FRAME_DT) / ((nb - end) * sensors.FRAME_DT)
            T[outside, :3, 3] = gt[end, :3, 3] + w[:, None] * (gt[nb, :3, 3] - gt[end, :3, 3])
    return T


def _box_at(box: dict, dt: np.ndarray, offset: float = 0.0) -> np.ndarray:
    """A mover's pose at the frame's time + dt from its boxes line (at the sweep's start, the frame's time and the
    sweep's end; the sweep centred on the lidar's reference instant, `offset` after the frame's time)."""
    poses = np.array([np.vstack([np.reshape(box["T_world_body"][k], (3, 4)), [0, 0, 0, 1]])
                      for k in ("sweep_start", "frame", "sweep_end")])
    return _interp_poses(poses, np.array([offset - 0.05, 0.0, offset + 0.05]), dt)


class _Lidar:
    """What a twin's scene.json says of its lidar: the true extrinsic, whether scans are compensated, the time
    offset and the per-beam biases, to take each return back to the surface point it measured."""

    def __init__(self, root) -> None:
        scene = json.loads((_seq(root) / "gt" / "scene.json").read_text())
        real = scene.get("realism")
        self.T_cam_velo = np.array(real["calibration"]["T_cam_velo_true"]) if real else sensors.T_CAM_VELO
        self.compensated = bool(scene["lidar"].get("motion_compensated", False))
        self.offset = real["rig"]["time_offset_s"] if real else 0.0
        fx = real["lidar_effects"] if real else None
        self.el_bias = np.array(fx["beam_elevation_bias_deg"]) + fx["elevation_offset_deg"] if fx else np.zeros(64)
        self.range_bias = np.array(fx["beam_range_bias_m"]) if fx else np.zeros(64)
        self.elevations = np.array(scene["lidar"]["elevations_deg"])

    def world(self, gt: np.ndarray, i: int, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns of frame i -> (N,3) the surface points measured (world) and (N,) their times after the frame's."""
        p = scan[:, :3].astype(np.float64)
        ref = self.offset
        T_ref = _ego_at(gt, i, np.array([ref]))[0] @ self.T_cam_velo
        own = p
        dt = ref + point_times(p)
        if self.compensated:  # each return back into the sensor at its own time (its azimuth gives the time)
            for _ in range(3):
                T_own = _ego_at(gt, i, dt) @ self.T_cam_velo
                rel = np.einsum("ij,kjl->kil", np.linalg.inv(T_ref), T_own)
                own = np.einsum("kji,kj->ki", rel[:, :3, :3], p - rel[:, :3, 3])
                dt = ref + point_times(own)
        rng = np.linalg.norm(own, axis=1)
        el = np.degrees(np.arcsin(own[:, 2] / rng))
        beam = np.argmin(np.abs(el[:, None] - self.elevations[None]), axis=1)
        true_el = np.radians(el + self.el_bias[beam])
        az = np.arctan2(own[:, 1], own[:, 0])
        r = rng - self.range_bias[beam]
        measured = np.column_stack([np.cos(true_el) * np.cos(az), np.cos(true_el) * np.sin(az), np.sin(true_el)])
        measured *= r[:, None]
        T = _ego_at(gt, i, dt) @ self.T_cam_velo
        return np.einsum("kij,kj->ki", T[:, :3, :3], measured) + T[:, :3, 3], dt


def _inside(box: dict, p_body: np.ndarray, margin: float) -> np.ndarray:
    L, W, H = box["size_lwh_m"]
    return ((np.abs(p_body[:, 0]) <= L / 2 + margin) & (np.abs(p_body[:, 1]) <= W / 2 + margin)
            & (p_body[:, 2] >= -margin - 0.1) & (p_body[:, 2] <= H + margin))


def test_twin_poses_are_the_followed_rows(twin_root, kitti_root):
    follow = kitti_root / "poses" / f"{SEQ}.txt"
    full = read_kitti_poses(follow)
    ds = KittiOdometry(twin_root, SEQ)
    assert len(ds) == N
    # frames 60:80: the followed rows re-based on frame 60, which becomes the origin
    np.testing.assert_allclose(ds.gt_T_world_cam, np.linalg.inv(full[FIRST]) @ full[FIRST:FIRST + N], atol=1e-8)
    scene = json.loads((_seq(twin_root) / "gt" / "scene.json").read_text())
    assert scene["follow"]["first_frame"] == FIRST and scene["follow"]["n_frames"] == N
    # a range from frame 0 writes the rows themselves
    first = load_followed(follow, "0:20")
    assert first.pose_file_text().splitlines() == follow.read_text().splitlines()[:20]
    np.testing.assert_allclose(first.T_world_cam, full[:20], atol=0)


def test_every_lidar_return_lands_on_its_own_depth(twin_root):
    ds = KittiOdometry(twin_root, SEQ)
    gt, K, lidar = ds.gt_T_world_cam, ds.calib.K, _Lidar(twin_root)
    assert lidar.compensated and ds.scans_compensated  # read as compensated: the loader does not deskew them again
    checked = movers_checked = 0
    for i in (0, 9, 19):
        scan, labels, depth, _, boxes = _frame_data(twin_root, i)
        assert len(scan) == len(labels) and len(scan) > 60_000
        X, dt = lidar.world(gt, i, scan)  # each return at its own time, the lidar's imperfections taken out
        assert np.abs(dt - lidar.offset).max() <= 0.05 + 1e-6
        by_id = {m["id"]: m for m in boxes["movers"]}
        for mid in np.unique(labels[labels > 0]):
            k = np.flatnonzero(labels == mid)
            B_then = _box_at(by_id[int(mid)], dt[k], lidar.offset)
            B_now = _box_at(by_id[int(mid)], np.zeros(1), lidar.offset)[0]
            body = np.einsum("kji,kj->ki", B_then[:, :3, :3], X[k] - B_then[:, :3, 3])
            X[k] = body @ B_now[:3, :3].T + B_now[:3, 3]  # where that surface point is at the frame's time
        Xc = (X - gt[i, :3, 3]) @ gt[i, :3, :3]  # into cam0 at the frame's time
        z = Xc[:, 2]
        front = np.flatnonzero(z > 1.0)
        u = K[0, 0] * Xc[front, 0] / z[front] + K[0, 2]
        v = K[1, 1] * Xc[front, 1] / z[front] + K[1, 2]
        inside = (u >= 1) & (u < depth.shape[1] - 2) & (v >= 1) & (v < depth.shape[0] - 2)
        f, u, v = front[inside], u[inside], v[inside]
        iu, iv = np.floor(u).astype(int), np.floor(v).astype(int)
        nb = np.stack([depth[iv + a, iu + b] for a in (-1, 0, 1, 2) for b in (-1, 0, 1, 2)], axis=1)
        tol = TOL_M + TOL_REL * z[f]
        lo, hi = nb.min(axis=1), nb.max(axis=1)  # inf where the camera sees the sky
        agree = (lo - tol <= z[f]) & (z[f] <= hi + tol)
        # Farther than every surface the camera sees there: hidden from cam0 behind a nearer one (the lidar sits
        # 0.27 m behind and 0.08 m above cam0, so it sees past poles and edges that cam0 does not). Never nearer:
        # the camera cannot look through a surface that the lidar hit.
        hidden = z[f] > hi + tol
        assert len(f) > 10_000
        assert (agree | hidden).all(), f"frame {i}: {int((~(agree | hidden)).sum())} returns nearer than cam0 sees"
        assert hidden.mean() < 0.01, f"frame {i}: {hidden.mean():.2%} of returns hidden from cam0"
        checked += len(f)
        movers_checked += int((labels[f] > 0).sum())
    assert movers_checked > 50, "no mover return was checked: the fixture's traffic is not in view"


def test_movers_are_inside_their_boxes_in_both_sensors(twin_root):
    ds = KittiOdometry(twin_root, SEQ)
    gt, K, lidar = ds.gt_T_world_cam, ds.calib.K, _Lidar(twin_root)
    seen_cam = seen_lidar = 0
    kinds = set()
    for i in range(0, N, 3):
        scan, labels, depth, ids, boxes = _frame_data(twin_root, i)
        X, dt = lidar.world(gt, i, scan)
        for box in boxes["movers"]:
            m = box["id"]
            v, u = np.nonzero(ids == m)
            assert box["pixels"] == len(u)
            if len(u):
                assert box["box2d_uv"] == [u.min(), v.min(), u.max() + 1, v.max() + 1]
                z = depth[v, u].astype(np.float64)
                pc = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
                pw = pc @ gt[i, :3, :3].T + gt[i, :3, 3]
                B = _box_at(box, np.zeros(1), lidar.offset)[0]
                body = (pw - B[:3, 3]) @ B[:3, :3]
                assert _inside(box, body, 0.08).all(), f"frame {i} mover {m}: camera pixels outside its box"
                seen_cam += len(u)
                kinds.add(box["kind"])
            k = np.flatnonzero(labels == m)
            assert box["lidar_returns"] == len(k)
            if len(k):
                pw = X[k]
                B = _box_at(box, dt[k], lidar.offset)
                body = np.einsum("kji,kj->ki", B[:, :3, :3], pw - B[:, :3, 3])
                assert _inside(box, body, 0.12).all(), f"frame {i} mover {m}: returns outside its box"
                seen_lidar += len(k)
    assert seen_cam > 500 and seen_lidar > 100, (seen_cam, seen_lidar)
    assert len(kinds) >= 2, kinds


def test_scenery_does_not_depend_on_the_driving_direction(kitti_root):
    path = load_followed(kitti_root / "poses" / "07.txt", "0:120")
    road = path.road_points()
    speed = path.speeds()
    fwd = build_world(Layout(road, road, speed, 5), 5)[0]
    back = build_world(Layout(road[::-1], road[::-1], speed[::-1], 5), 5)[0]

    def canon(town):
        tri = np.sort(np.round(town.vertices[town.triangles.astype(np.int64)], 3).reshape(-1, 9), axis=0)
        return tri

    assert len(fwd.triangles) == len(back.triangles) > 20_000
    np.testing.assert_allclose(canon(fwd), canon(back), atol=2e-3)


def test_shadow_edges_and_exposure_are_recorded(twin_root):
    seq = _seq(twin_root)
    edges = cv2.imread(str(seq / "gt" / "shadow_edges" / "000010.png"), cv2.IMREAD_UNCHANGED)
    image = cv2.imread(str(seq / "image_0" / "000010.png"), cv2.IMREAD_UNCHANGED)
    assert edges.shape == image.shape and set(np.unique(edges)) <= {0, 255}
    assert 0.001 < (edges > 0).mean() < 0.2
    # a shadow edge is a step in brightness: the darker side is the shadow
    g = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.0)
    grad = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    assert grad[edges > 0].mean() > 3.0 * grad[edges == 0].mean()
    scene = json.loads((seq / "gt" / "scene.json").read_text())
    gains = scene["camera"]["exposure_gains"]
    assert len(gains) == N and all(0.5 <= g <= 2.5 for g in gains)
    sky = image[:40][np.load(seq / "gt" / "depth" / "000010.npy")[:40] == np.inf]
    assert len(sky) > 200
    assert sky.std() > 2.0  # not a flat sky (a realistic camera may clip most of it, as KITTI's does)


def test_lidar_models_and_sweep_times():
    assert sweep_time(np.array([0.0]))[0] == 0.0
    assert sweep_time(np.array([np.pi / 2]))[0] == pytest.approx(-0.025)  # the left is swept before the front
    assert sweep_time(np.array([-np.pi / 2]))[0] == pytest.approx(0.025)
    for model in LIDAR_MODELS.values():
        rays = model.rays()
        assert rays.shape == (len(model.elevations_deg) * model.azimuth_steps, 3)
        np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-6)
        t = model.ray_times()
        assert t.min() > -0.05 and t.max() < 0.05 and np.all(np.diff(t) >= 0)
        np.testing.assert_allclose(point_times(rays), t, atol=1e-6)
    assert len(LIDAR_MODELS["os128"].elevations_deg) == 128 and len(LIDAR_MODELS["vlp16"].elevations_deg) == 16


def test_bad_follow_input_names_file_and_line(tmp_path, kitti_root):
    bad = tmp_path / "poses.txt"
    lines = (kitti_root / "poses" / "07.txt").read_text().splitlines()[:10]
    lines[4] = " ".join(lines[4].split()[:11])
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(SynthError, match=r"poses\.txt:5: expected 12 numbers"):
        load_followed(bad)
    with pytest.raises(SynthError, match="has 1101 poses"):
        load_followed(kitti_root / "poses" / "07.txt", "0:5000")
    with pytest.raises(SynthError, match="A:B"):
        load_followed(kitti_root / "poses" / "07.txt", "20")


def test_kiss_icp_tracks_a_twin(twin_root):
    from plvo.data.registry import open_dataset
    from plvo_eval.kiss import KissOptions, run_kiss
    from plvo_eval.kitti_metric import short_relative_error
    from plvo_eval.tasks import anchor

    ds = open_dataset(twin_root, SEQ)
    out = run_kiss(ds, KissOptions())
    gt = ds.gt_T_world_cam
    est = anchor(out.poses, gt[0])
    driven = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    assert driven > 12.0
    est_driven = float(np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1).sum())
    assert est_driven == pytest.approx(driven, rel=0.05)  # not stuck at zero motion
    drift = float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
    assert drift < 0.03 * driven, drift
    short = short_relative_error(gt, est, lengths=(10.0,))
    assert short.t_err_pct < 3.0


def test_ground_follows_the_trajectorys_height(twin_root, kitti_root):
    scene = json.loads((_seq(twin_root) / "gt" / "scene.json").read_text())
    heights = np.array(scene["camera"]["height_above_ground_m"])
    assert len(heights) == N and np.abs(heights - sensors.CAMERA_HEIGHT_M).max() < 0.05
    # 01: 2.4 km of highway climbing 67 m; the ground stays 1.65 m under cam0 all the way
    path = load_followed(kitti_root / "poses" / "01.txt")
    layout = Layout(path.context_road, path.file_road, path.file_speed, 0, path.context_real)
    cam = path.T_town_cam[:, :3, 3]
    above = cam[:, 2] - layout.height(cam[:, :2])
    assert np.ptp(cam[:, 2]) > 50.0
    assert np.percentile(np.abs(above - sensors.CAMERA_HEIGHT_M), 99) < 0.06
    assert above.min() > sensors.CAMERA_HEIGHT_M - 0.1
    # 08 drives its streets again at ground-truth heights up to 6 m apart: the ground follows the lower pass,
    # so cam0 is never below it
    path = load_followed(kitti_root / "poses" / "08.txt")
    layout = Layout(path.context_road, path.file_road, path.file_speed, 0, path.context_real)
    cam = path.T_town_cam[:, :3, 3]
    assert (cam[:, 2] - layout.height(cam[:, :2])).min() > 1.0


def _cast_every_ray(traffic, origins, dirs, times):
    """Reference for Traffic.cast's nearest mover hit: every ray against every live mover's mesh, no sphere test."""
    import open3d as o3d

    t_best, ids = np.full(len(dirs), np.inf, np.float32), np.zeros(len(dirs), np.uint16)
    uniq, inv = np.unique(np.broadcast_to(np.asarray(times, np.float64), len(dirs)), return_inverse=True)
    for m in traffic.movers:
        T, alive = traffic.pose(m, uniq)
        T, ok = T[inv.ravel()], alive[inv.ravel()]
        o_body = np.einsum("kji,kj->ki", T[:, :3, :3], origins - T[:, :3, 3])
        d_body = np.einsum("kji,kj->ki", T[:, :3, :3], dirs)
        rays = o3d.core.Tensor.from_numpy(np.concatenate([o_body, d_body], axis=1).astype(np.float32))
        th = np.where(ok, traffic.scenes[m.shape].cast_rays(rays)["t_hit"].numpy(), np.inf)
        better = th < t_best
        t_best[better], ids[better] = th[better], m.id
    return t_best, ids


def test_mover_casts_keep_every_hit(kitti_root):
    """Traffic.cast tests each mover's bounding sphere before casting into its mesh (one matrix-vector product a
    mover when the rays share an instant); no hit of the camera's rays (one origin), of rays from many origins at
    one instant (shadow rays) or of a rolling sweep (a time a column) may be lost by it."""
    from plvo_synth.twin.follow import PoseInterpolator
    from plvo_synth.twin.generate import TwinSettings, build_twin

    twin = build_twin(TwinSettings(str(kitti_root / "poses" / f"{SEQ}.txt"), "60:80", traffic=8), SEQ)
    r, traffic = twin.renderer, twin.traffic
    poses = PoseInterpolator(twin.path.T_town_cam)
    hits = 0
    for i in (0, 10, 19):
        T, t = twin.path.T_town_cam[i], i * sensors.FRAME_DT
        dirs = r._cast(r._cam_dirs, T)[3][:, 3:].astype(np.float64)
        origin = np.broadcast_to(T[:3, 3].astype(np.float64), dirs.shape)
        want_t, want_ids = _cast_every_ray(traffic, origin, dirs, t)
        for o, when in ((origin, t), (np.array(origin), np.full(len(dirs), t))):  # one origin; many, one instant
            got_t, got_ids = traffic.cast(o, dirs, when)[:2]
            np.testing.assert_array_equal(got_ids, want_ids)
            np.testing.assert_allclose(got_t, want_t, rtol=1e-6)
        hits += int((want_ids > 0).sum())
        T_cols = poses(t + r._lidar_dt[:: r._beams]) @ sensors.T_CAM_VELO
        o = np.repeat(T_cols[:, :3, 3], r._beams, axis=0)
        d = np.einsum("kij,kj->ki", np.repeat(T_cols[:, :3, :3], r._beams, axis=0), r._lidar_dirs.astype(np.float64))
        want_t, want_ids = _cast_every_ray(traffic, o, d, t + r._lidar_dt)
        got_t, got_ids = traffic.cast(o, d, t + r._lidar_dt)[:2]
        np.testing.assert_array_equal(got_ids, want_ids)
        hits += int((want_ids > 0).sum())
    assert hits > 1000, hits  # movers were in view
