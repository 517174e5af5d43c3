"""Point and line matching: exact criteria on hand-made feature sets, precision on warped drawings and KITTI 04."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from features_eval import flow_predicted_segments, judge_lines, judge_points, read_kitti_poses, read_p0

from plvo.config import LineConfig, MatchingConfig, OrbConfig
from plvo.features.extract import extract_features
from plvo.features.matching import hamming_matrix, hamming_pairs, match_features, match_lines, match_points
from plvo.types import FeatureSet

W, H = 1241, 376


def feature_set(kp=None, desc=None, seg=None, ldesc=None) -> FeatureSet:
    kp = np.zeros((0, 2)) if kp is None else np.asarray(kp, float)
    seg = np.zeros((0, 4)) if seg is None else np.asarray(seg, float)
    return FeatureSet(
        keypoints=kp, kp_octave=np.zeros(len(kp), np.int32), kp_angle=np.zeros(len(kp)),
        kp_response=np.ones(len(kp)), descriptors=np.zeros((len(kp), 32), np.uint8) if desc is None else desc,
        segments=seg, line_descriptors=np.zeros((len(seg), 32), np.uint8) if ldesc is None else ldesc,
        raw_segments=seg, segment_sources=tuple(np.array([i]) for i in range(len(seg))), image_size=(W, H),
    )


def scene(seed: int = 0) -> np.ndarray:
    """Texture plus bars of various angles and widths."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.normal(128, 50, (H, W)).astype(np.float32), (0, 0), 2.0)
    for _ in range(14):
        c = rng.uniform([100, 60], [W - 100, H - 60])
        th = rng.uniform(0, np.pi)
        d = rng.uniform(60, 160) * np.array([np.cos(th), np.sin(th)])
        cv2.line(img, tuple(np.round(c - d).astype(int)), tuple(np.round(c + d).astype(int)),
                 float(rng.choice([20, 240])), int(rng.integers(4, 12)), cv2.LINE_AA)
    return np.clip(img, 0, 255).astype(np.uint8)


def warp(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    return cv2.warpAffine(img, A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def apply(A: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ A[:, :2].T + A[:, 2]


A_MOTION = cv2.getRotationMatrix2D((W / 2, H / 2), 2.0, 1.03) + np.array([[0, 0, 12.0], [0, 0, -4.0]])


def test_hamming_helpers_agree_with_bit_counts():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    want = np.unpackbits(a[:, None] ^ b[None], axis=2).sum(axis=2)
    np.testing.assert_array_equal(hamming_matrix(a, b), want)
    i, j = rng.integers(0, 50, 100), rng.integers(0, 40, 100)
    np.testing.assert_array_equal(hamming_pairs(a, b, i, j), want[i, j])


def test_point_ratio_mutual_and_window():
    rng = np.random.default_rng(1)
    d = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    near = d.copy()
    near[:, 0] ^= 0b111  # 3 bits off
    prev = feature_set(kp=[[100, 100], [300, 100], [500, 100], [700, 100]], desc=d)
    cur = feature_set(kp=[[110, 100], [310, 100], [510, 100], [900, 300]], desc=near)
    cfg = MatchingConfig()
    m = match_points(prev, cur, cfg)
    assert m.pairs.tolist() == [[0, 0], [1, 1], [2, 2], [3, 3]]
    # a prediction far from point 3's match puts it out of the window
    pred = prev.keypoints + [10.0, 0.0]
    m = match_points(prev, cur, cfg, pred)
    assert m.pairs.tolist() == [[0, 0], [1, 1], [2, 2]]
    # NaN rows search everywhere
    pred[3] = np.nan
    assert match_points(prev, cur, cfg, pred).pairs.tolist() == [[0, 0], [1, 1], [2, 2], [3, 3]]
    # ratio test: an ambiguous twin removes the match
    twin = feature_set(kp=[[110, 100], [120, 100]], desc=np.stack([near[0], near[0]]))
    assert len(match_points(feature_set(kp=[[100, 100]], desc=d[:1]), twin, cfg)) == 0


def test_line_geometric_criteria():
    rng = np.random.default_rng(2)
    ld = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    prev = feature_set(seg=[[100, 100, 300, 100]], ldesc=ld)
    cfg = MatchingConfig()

    def matched(seg, pred=None):
        return len(match_lines(prev, feature_set(seg=[seg], ldesc=ld), cfg, pred)) == 1

    assert matched([102, 101, 302, 101])
    assert not matched([300, 100, 100, 100])  # reversed polarity
    th = np.radians(2.5)  # over the 2 deg bound
    assert not matched([100, 100, 100 + 200 * np.cos(th), 100 + 200 * np.sin(th)])
    assert not matched([100, 100, 325, 100])  # 11 % longer
    assert matched([100, 100, 315, 100])  # 7 % longer (midpoint 7.5 px away: unpredicted bound 40)
    assert not matched([100, 150, 300, 150])  # 50 px away, no prediction
    # with a prediction the paper's 5 px bound applies around the predicted segment
    assert matched([100, 150, 300, 150], np.array([[101, 148, 301, 148]]))
    assert not matched([100, 150, 300, 150], np.array([[100, 142, 300, 142]]))
    assert matched([102, 101, 302, 101], np.full((1, 4), np.nan))  # NaN row: unpredicted bounds


def test_matching_on_a_warped_drawing():
    img = scene()
    cur_img = warp(img, A_MOTION)
    a = extract_features(img, OrbConfig(), LineConfig())
    b = extract_features(cur_img, OrbConfig(), LineConfig())
    cfg = MatchingConfig()
    pts = match_points(a, b, cfg)
    err = np.linalg.norm(apply(A_MOTION, a.keypoints[pts.pairs[:, 0]]) - b.keypoints[pts.pairs[:, 1]], axis=1)
    tol = 2.0 * OrbConfig().scale_factor ** a.kp_octave[pts.pairs[:, 0]]  # 2 px at the point's pyramid level
    assert len(pts) > 300 and np.mean(err < tol) > 0.95
    # with the true motion as prediction: as many matches, still right
    pred = match_points(a, b, cfg, apply(A_MOTION, a.keypoints))
    err_p = np.linalg.norm(apply(A_MOTION, a.keypoints[pred.pairs[:, 0]]) - b.keypoints[pred.pairs[:, 1]], axis=1)
    tol_p = 2.0 * OrbConfig().scale_factor ** a.kp_octave[pred.pairs[:, 0]]
    assert len(pred) >= 0.9 * len(pts) and np.mean(err_p < tol_p) > 0.95

    pred_seg = np.c_[apply(A_MOTION, a.segments[:, :2]), apply(A_MOTION, a.segments[:, 2:])]
    lines = match_lines(a, b, cfg, pred_seg)
    s0 = pred_seg[lines.pairs[:, 0]]
    s1 = b.segments[lines.pairs[:, 1]]
    u = (s0[:, 2:] - s0[:, :2]) / np.linalg.norm(s0[:, 2:] - s0[:, :2], axis=1, keepdims=True)
    n = np.c_[-u[:, 1], u[:, 0]]
    off = np.maximum(np.abs(np.einsum("ij,ij->i", s1[:, :2] - s0[:, :2], n)),
                     np.abs(np.einsum("ij,ij->i", s1[:, 2:] - s0[:, :2], n)))
    assert len(lines) >= 0.5 * min(a.n_lines, b.n_lines)
    assert np.mean(off < 2.0) > 0.95
    both = match_features(a, b, cfg, None, pred_seg)
    np.testing.assert_array_equal(both.lines.pairs, lines.pairs)
    np.testing.assert_array_equal(both.points.pairs, pts.pairs)


@pytest.fixture(scope="module")
def kitti_features(kitti_root):
    K = read_p0(kitti_root / "sequences" / "04" / "calib.txt")
    T = read_kitti_poses(kitti_root / "poses" / "04.txt")
    frames = sorted({f for i in range(0, 50, 5) for f in (i, i + 1)})
    fs = {}
    for f in frames:
        img = cv2.imread(str(kitti_root / "sequences" / "04" / "image_0" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        fs[f] = extract_features(img, OrbConfig(), LineConfig())
    return K, T, fs


def test_kitti_point_and_line_precision(kitti_features):
    """Consecutive frames of KITTI 04 judged with the ground-truth motion (see tests/helpers/features_eval.py).

    Measured on all 50 pairs: points 0.869 right (0.903 outside the van ahead, which moves with the camera),
    ~259 a pair; lines without prediction 0.57 of the judgeable right, ~13 a pair. Wrong line matches are on
    the van and on the repetitive hatched road marking of frames 36-40.
    """
    K, T, fs = kitti_features
    cfg = MatchingConfig()
    p_ok = p_n = l_ok = l_judged = l_n = 0
    for i in range(0, 50, 5):
        a, b = fs[i], fs[i + 1]
        T10 = np.linalg.inv(T[i + 1]) @ T[i]
        m = match_points(a, b, cfg)
        ok = judge_points(K, T10, a.keypoints[m.pairs[:, 0]], b.keypoints[m.pairs[:, 1]])
        p_ok, p_n = p_ok + ok.sum(), p_n + len(ok)
        pred = flow_predicted_segments(a.keypoints, b.keypoints, m.pairs, a.segments)
        ml = match_lines(a, b, cfg, pred)
        right, judged = judge_lines(K, T10, a.segments[ml.pairs[:, 0]], b.segments[ml.pairs[:, 1]])
        l_ok, l_judged, l_n = l_ok + right.sum(), l_judged + judged.sum(), l_n + len(ml)
    assert p_n / 10 > 150
    assert p_ok / p_n > 0.8
    assert l_n / 10 >= 5
    assert l_judged >= 20 and l_ok / l_judged > 0.45


def test_points_only_extraction_has_no_lines():
    img = scene(3)
    fs = extract_features(img, OrbConfig(), LineConfig(), points_only=True)
    assert fs.n_lines == 0 and fs.line_descriptors.shape == (0, 32) and fs.n_points > 900
    seq = extract_features(img, OrbConfig(), dataclasses.replace(LineConfig(), in_thread=False))
    par = extract_features(img, OrbConfig(), LineConfig())
    one_lbd = extract_features(img, OrbConfig(), LineConfig(), split_lbd=False)  # as the features worker runs it
    assert len(par.segments) >= 16  # enough for the LBD split to be used
    for other in (seq, one_lbd):
        np.testing.assert_array_equal(other.segments, par.segments)
        np.testing.assert_array_equal(other.line_descriptors, par.line_descriptors)
        np.testing.assert_array_equal(other.descriptors, par.descriptors)


def test_window_pairs_match_brute_force():
    from plvo.features.matching import window_pairs

    rng = np.random.default_rng(4)
    pts = rng.uniform([0, 0], [W, H], (400, 2))
    centres = np.vstack([rng.uniform([-80, -80], [W + 80, H + 80], (300, 2)), [[np.nan, 5.0]], pts[:5]])
    i, j = window_pairs(centres, pts, 60.0)
    d2 = ((centres[:, None] - pts[None]) ** 2).sum(2)
    want = set(zip(*np.nonzero(d2 <= 60.0**2)))
    assert set(zip(i.tolist(), j.tolist())) == want and len(i) == len(want)
    assert np.all(np.diff(i) >= 0)  # grouped by centre


def test_windowed_selection_equals_masked_dense_selection():
    """The sparse path (pairs in the window, NaN rows against all) picks what argmin over the masked dense
    matrix picks, ties included: descriptors drawn from a small pool make many equal distances."""
    from plvo.features.matching import _BIG, _best_mutual

    rng = np.random.default_rng(5)
    pool = rng.integers(0, 256, (12, 32), dtype=np.uint8)
    for trial in range(20):
        n, m = rng.integers(20, 80, 2)
        a = feature_set(kp=rng.uniform([0, 0], [300, 200], (n, 2)), desc=pool[rng.integers(0, 12, n)])
        b = feature_set(kp=rng.uniform([0, 0], [300, 200], (m, 2)), desc=pool[rng.integers(0, 12, m)])
        pred = a.keypoints + rng.normal(0, 20, (n, 2))
        pred[rng.random(n) < 0.2] = np.nan
        cfg = dataclasses.replace(MatchingConfig(), point_window_px=50.0, point_max_hamming=256)
        got = match_points(a, b, cfg, pred)
        dist = hamming_matrix(a.descriptors, b.descriptors)
        far = ((pred[:, None] - b.keypoints[None]) ** 2).sum(2) > 50.0**2
        dist[np.all(np.isfinite(pred), 1)[:, None] & far] = _BIG
        want = _best_mutual(dist, cfg.point_max_hamming, cfg.point_ratio, cfg.point_mutual)
        assert got.pairs.tolist() == want.pairs.tolist(), trial
        np.testing.assert_array_equal(got.distance, want.distance)


def test_line_bound_per_predicted_row():
    ld = np.random.default_rng(6).integers(0, 256, (2, 32), dtype=np.uint8)
    prev = feature_set(seg=[[100, 100, 300, 100], [100, 250, 300, 250]], ldesc=ld)
    cur = feature_set(seg=[[100, 108, 300, 108], [100, 258, 300, 258]], ldesc=ld)  # both 8 px below
    pred = prev.segments.copy()
    cfg = MatchingConfig()
    assert len(match_lines(prev, cur, cfg, pred)) == 0  # the paper's 5 px
    m = match_lines(prev, cur, cfg, pred, predicted_bound_px=np.array([10.0, 5.0]))
    assert m.pairs.tolist() == [[0, 0]]
    assert len(match_lines(prev, cur, cfg, pred, predicted_bound_px=10.0)) == 2
