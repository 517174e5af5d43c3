"""LSD + repair (chaining and merging) + LBD on images drawn for the purpose, and the repair's bookkeeping."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from plvo.config import LineConfig
from plvo.errors import PlvoError
from plvo.features.lbd import compute_lbd
from plvo.features.lines import detect_lines, detect_lsd, repair_segments, repair_tolerances, segment_lengths

W, H = 1241, 376
SS = 4  # supersampling of the drawings


def draw(polygons: list[tuple[np.ndarray, int]], background: int = 60, seed: int = 0) -> np.ndarray:
    """Anti-aliased filled polygons (vertices in pixels, pixel centres at integers), slight blur and noise."""
    hi = np.full((H * SS, W * SS), background, np.uint8)
    for pts, value in polygons:
        p = (np.asarray(pts, float) + 0.5) * SS - 0.5
        cv2.fillPoly(hi, [np.round(p * 16).astype(np.int32)], int(value), cv2.LINE_8, 4)
    img = cv2.resize(hi, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    img += np.random.default_rng(seed).normal(0.0, 2.0, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def bar(p0, p1, thickness: float) -> np.ndarray:
    """Rectangle with one long side p0 -> p1, extending `thickness` to the side of the normal (-dy, dx)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-u[1], u[0]])
    return np.array([p0, p1, p1 + thickness * n, p0 + thickness * n])


def occluders(p0, p1, at, width: float, value: int) -> list[tuple[np.ndarray, int]]:
    """Small rectangles across the edge p0 -> p1 at fractions `at`, `width` px along it: they break LSD."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-u[1], u[0]])
    out = []
    for t in at:
        c = p0 + t * (p1 - p0)
        out.append((np.array([c - width / 2 * u - 8 * n, c + width / 2 * u - 8 * n,
                              c + width / 2 * u + 8 * n, c - width / 2 * u + 8 * n]), value))
    return out


def on_line(seg: np.ndarray, p0, p1, tol: float) -> np.ndarray:
    """(N,) bool: both endpoints of each segment within tol px of the infinite line p0 p1."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-u[1], u[0]])
    d0 = np.abs((seg[:, :2] - p0) @ n)
    d1 = np.abs((seg[:, 2:] - p0) @ n)
    return (d0 < tol) & (d1 < tol)


def oriented_like(seg: np.ndarray, p0, p1) -> np.ndarray:
    e = seg.reshape(2, 2)
    return e if np.dot(e[1] - e[0], np.subtract(p1, p0)) > 0 else e[::-1]


EDGES = [((150.0, 120.3), (1050.0, 210.7)), ((120.0, 95.0), (980.0, 40.5)), ((200.0, 300.2), (1100.0, 300.9))]


@pytest.mark.parametrize("scale,width", [(0.5, 5.0), (0.4, 8.0)])  # occluders LSD does not see through
@pytest.mark.parametrize("p0,p1", EDGES)
def test_broken_edge_comes_back_as_one_segment(p0, p1, scale, width):
    """Six occluders break each edge; the repair joins the pieces, at the default LSD scale and at a coarser one
    (whose repair distances grow with LSD's pixel, repair_tolerances). Distances below are for LSD at 0.5, grown
    alike: LSD's pixel is 1 / scale of the image's."""
    cfg = dataclasses.replace(LineConfig(), lsd_scale=scale)
    g = 0.5 / scale
    at = [0.12, 0.27, 0.41, 0.58, 0.73, 0.88]
    clean = draw([(bar(p0, p1, 40), 200)])
    broken = draw([(bar(p0, p1, 40), 200)] + occluders(p0, p1, at, width, 120))

    raw = detect_lsd(broken, cfg)
    pieces = raw[on_line(raw, p0, p1, 1.5 * g) & (segment_lengths(raw) > 20)]
    assert len(pieces) >= 3, "the occluders must break LSD's edge for this test to mean anything"

    out = repair_segments(raw, cfg)
    hits = np.flatnonzero(on_line(out.segments, p0, p1, 1.0 * g))
    assert len(hits) == 1, f"expected one segment on the edge, got {len(hits)}"
    k = hits[0]
    assert len(out.sources[k]) >= len(pieces)
    # the sources are raw segments on that edge
    assert np.all(on_line(raw[out.sources[k]], p0, p1, 1.5 * g))

    # same as LSD on the unbroken edge, within 1 px (at 0.5)
    ref = detect_lines(clean, cfg)
    ref_k = np.flatnonzero(on_line(ref.segments, p0, p1, 1.0 * g))
    assert len(ref_k) == 1
    got, want = oriented_like(out.segments[k], p0, p1), oriented_like(ref.segments[ref_k[0]], p0, p1)
    assert np.max(np.linalg.norm(got - want, axis=1)) < 1.0 * g
    # and on the drawn edge: sub-pixel across it; along it LSD itself stops short of a corner by up to
    # 1 px of its own image (measured 0.6-2.5 px at lsd_scale 0.5)
    truth = np.array([p0, p1])
    u = (truth[1] - truth[0]) / np.linalg.norm(truth[1] - truth[0])
    n = np.array([-u[1], u[0]])
    assert np.max(np.abs((got - truth) @ n)) < 0.3 * g
    assert np.max(np.abs((got - truth) @ u)) < 3.0 * g


@pytest.mark.parametrize("p0,p1", EDGES)
def test_broken_edge_is_joined_at_lsd_scale_035(p0, p1):
    """At LSD scale 0.35 the pieces lie up to ~2 px off each other's line: with the distances set for 0.5 an edge
    stays in pieces; grown with LSD's pixel (repair_tolerances) each edge is one segment again, made of all its
    pieces and on the drawn line. (Its ends are LSD's: up to 8 px short of a corner at this scale, measured.)"""
    cfg = dataclasses.replace(LineConfig(), lsd_scale=0.35)
    assert repair_tolerances(cfg).chain_offset_px > cfg.chain_offset_px
    broken = draw([(bar(p0, p1, 40), 200)] + occluders(p0, p1, [0.12, 0.27, 0.41, 0.58, 0.73, 0.88], 7.0, 120))
    raw = detect_lsd(broken, cfg)
    pieces = on_line(raw, p0, p1, 2.0) & (segment_lengths(raw) > 20)
    assert pieces.sum() >= 3, "the occluders must break LSD's edge for this test to mean anything"
    out = repair_segments(raw, cfg)
    hits = np.flatnonzero(on_line(out.segments, p0, p1, 1.0))
    assert len(hits) == 1, f"expected one segment on the edge, got {len(hits)}"
    assert set(np.flatnonzero(pieces)) <= set(out.sources[hits[0]].tolist())


def test_repair_distances_hold_at_lsd_scale_05_and_finer():
    """The defaults' repair is the configured one, bit for bit: the distances grow only below LSD scale 0.5."""
    for scale in (0.5, 1.0):
        cfg = dataclasses.replace(LineConfig(), lsd_scale=scale)
        assert repair_tolerances(cfg) is cfg
    cfg = dataclasses.replace(LineConfig(), lsd_scale=0.25)
    grown = repair_tolerances(cfg)
    assert (grown.chain_offset_px, grown.chain_endpoint_px, grown.merge_distance_px) == (
        2 * cfg.chain_offset_px, 2 * cfg.chain_endpoint_px, 2 * cfg.merge_distance_px)


def test_chaining_restores_a_long_edge_at_full_resolution():
    """At lsd_scale 1 small occluders already break LSD; chained endpoints within 1 px of the drawn ones."""
    cfg = dataclasses.replace(LineConfig(), lsd_scale=1.0)
    p0, p1 = EDGES[0]
    broken = draw([(bar(p0, p1, 40), 200)] + occluders(p0, p1, [0.2, 0.4, 0.6, 0.8], 3.0, 130))
    raw = detect_lsd(broken, cfg)
    assert np.sum(on_line(raw, p0, p1, 1.5) & (segment_lengths(raw) > 20)) >= 3
    out = repair_segments(raw, cfg)
    hits = np.flatnonzero(on_line(out.segments, p0, p1, 1.0))
    assert len(hits) == 1
    got = oriented_like(out.segments[hits[0]], p0, p1)
    assert np.max(np.linalg.norm(got - np.array([p0, p1]), axis=1)) < 1.0


@pytest.mark.parametrize("scale,tol", [(0.5, 2.5), (1.0, 0.5)])
def test_double_edge_two_px_apart_becomes_one(scale, tol):
    """At lsd_scale 0.5 LSD sees the 2 px stripe as a 1 px line and finds one of its blurred sides (measured
    2.2 px from the middle); at 1.0 it finds both edges and the merge puts the segment in the middle."""
    cfg = dataclasses.replace(LineConfig(), lsd_scale=scale)
    p0, p1 = (180.0, 150.4), (1000.0, 230.0)
    img = draw([(bar(p0, p1, 2.0), 220)])
    raw = detect_lsd(img, cfg)
    out = repair_segments(raw, cfg)
    near = on_line(out.segments, p0, p1, 3.0) & (segment_lengths(out.segments) > 100)
    assert near.sum() == 1, f"{near.sum()} segments along the 2 px stripe"
    k = np.flatnonzero(near)[0]
    # it runs along the stripe's middle (1 px from either edge)
    mid0 = bar(p0, p1, 1.0)[3]
    mid1 = bar(p0, p1, 1.0)[2]
    assert np.all(on_line(out.segments[k : k + 1], mid0, mid1, tol))
    assert segment_lengths(out.segments[k : k + 1])[0] > 0.95 * np.hypot(*np.subtract(p1, p0)) - 6


def test_raw_double_edge_is_two_segments_at_full_resolution():
    """At lsd_scale 1 LSD sees both edges of a 2 px stripe: the merge, not LSD, makes them one."""
    cfg = dataclasses.replace(LineConfig(), lsd_scale=1.0)
    p0, p1 = (180.0, 150.4), (1000.0, 230.0)
    raw = detect_lsd(draw([(bar(p0, p1, 2.0), 220)]), cfg)
    long_raw = raw[on_line(raw, p0, p1, 3.0) & (segment_lengths(raw) > 100)]
    side = (long_raw[:, :2] + long_raw[:, 2:]) / 2 - np.asarray(p0)
    n = bar(p0, p1, 1.0)[3] - np.asarray(p0)
    offsets = side @ n
    assert offsets.min() < 0.8 and offsets.max() > 1.2, "expected raw segments on both edges"
    out = repair_segments(raw, cfg)
    assert np.sum(on_line(out.segments, p0, p1, 3.0) & (segment_lengths(out.segments) > 100)) == 1


def test_parallel_edges_ten_px_apart_stay_two():
    cfg = LineConfig()
    p0, p1 = (180.0, 150.4), (1000.0, 230.0)
    out = detect_lines(draw([(bar(p0, p1, 10.0), 220)]), cfg)
    top = on_line(out.segments, p0, p1, 1.0)
    bottom = on_line(out.segments, bar(p0, p1, 10.0)[3], bar(p0, p1, 10.0)[2], 1.0)
    assert top.sum() == 1 and bottom.sum() == 1


@pytest.mark.parametrize("angle_deg", [8.0, 20.0, 90.0])
def test_edges_at_other_angles_are_not_merged(angle_deg):
    """Two bars meeting end to end at an angle: their edges touch but are not collinear."""
    cfg = LineConfig()
    a0 = np.array([200.0, 200.0])
    a1 = np.array([600.0, 200.0])
    th = np.radians(angle_deg)
    a2 = a1 + 300.0 * np.array([np.cos(th), -np.sin(th)])
    img = draw([(bar(a0, a1, -30.0), 200), (bar(a1, a2, -30.0), 200)])
    out = detect_lines(img, cfg)
    first = on_line(out.segments, a0, a1, 1.0) & (segment_lengths(out.segments) > 200)
    second = on_line(out.segments, a1, a2, 1.0) & (segment_lengths(out.segments) > 150)
    assert first.sum() == 1 and second.sum() == 1
    assert not np.any(first & second)
    # neither absorbed the other: each ends near the junction
    k1, k2 = np.flatnonzero(first)[0], np.flatnonzero(second)[0]
    assert segment_lengths(out.segments[k1 : k1 + 1])[0] < 410
    assert segment_lengths(out.segments[k2 : k2 + 1])[0] < 310


def test_short_segments_are_dropped_and_sources_are_consistent():
    cfg = LineConfig()
    polys = [(bar((100.0 + 60 * k, 60.0), (100.0 + 60 * k + 30.0, 60.0), 20.0), 200) for k in range(8)]
    polys.append((bar((150.0, 250.0), (900.0, 280.0), 30.0), 200))
    out = detect_lines(draw(polys), cfg)
    assert np.all(segment_lengths(out.segments) >= cfg.min_length_px)
    assert not np.any(on_line(out.segments, (100.0, 60.0), (600.0, 60.0), 2.0))  # 30 px bars are gone
    assert len(out.sources) == len(out.segments)
    used = np.concatenate(out.sources)
    assert len(np.unique(used)) == len(used), "a raw segment feeds at most one output segment"
    assert used.min() >= 0 and used.max() < len(out.raw)
    for seg, src in zip(out.segments, out.sources):
        # every source lies along its output segment
        assert np.all(on_line(out.raw[src], seg[:2], seg[2:], cfg.merge_distance_px + 0.5))
    # the longest first
    assert np.all(np.diff(segment_lengths(out.segments)) <= 1e-9)


def test_repair_of_given_pieces_is_exact():
    """Collinear pieces with small gaps (no image): one segment, exact endpoints, sources = all pieces."""
    cfg = LineConfig()
    xs = [(100, 160), (166, 240), (247, 300), (305, 420), (428, 500)]
    raw = np.array([[x0, 50 + 0.1 * x0, x1, 50 + 0.1 * x1] for x0, x1 in xs], float)
    raw = np.vstack([raw, [[100, 200, 400, 200], [100, 202, 400, 202.5]]])  # a double edge, 2-2.5 px apart
    out = repair_segments(raw, cfg)
    assert len(out.segments) == 2
    k = int(np.argmin(np.abs(out.segments[:, 1] - 60)))
    np.testing.assert_allclose(out.segments[k], [100, 60, 500, 100], atol=1e-6)
    assert sorted(out.sources[k].tolist()) == [0, 1, 2, 3, 4]
    assert sorted(out.sources[1 - k].tolist()) == [5, 6]


def test_lbd_descriptors_follow_segments():
    cfg = LineConfig()
    img = draw([(bar((150.0, 120.3), (1050.0, 210.7), 40), 200), (bar((300.0, 330.0), (900.0, 250.0), 15), 150)])
    out = detect_lines(img, cfg)
    desc = compute_lbd(img, out.segments)
    assert desc.shape == (len(out.segments), 32) and desc.dtype == np.uint8
    # row i belongs to segment i: computing a subset in another order permutes the rows
    order = np.arange(len(out.segments))[::-1]
    np.testing.assert_array_equal(compute_lbd(img, out.segments[order]), desc[order])
    # a slightly shifted copy of the image gives near-identical descriptors for the same segments
    shifted = np.roll(img, 1, axis=1)
    desc2 = compute_lbd(shifted, out.segments + [1.0, 0.0, 1.0, 0.0])
    ham = np.unpackbits(desc ^ desc2, axis=1).sum(axis=1)
    assert np.all(ham < 40)
    assert compute_lbd(img, np.zeros((0, 4))).shape == (0, 32)


def test_bad_image_raises():
    with pytest.raises(PlvoError, match="LSD"):
        detect_lsd(np.zeros((10, 10, 3), np.uint8), LineConfig())
    with pytest.raises(PlvoError, match="LBD"):
        compute_lbd(np.zeros((10, 10), np.float32), np.zeros((1, 4)))


def test_the_reused_detector_finds_what_a_fresh_one_finds():
    """detect_lsd keeps one LSD per thread between images: across images of other content and size it must give
    exactly what a new detector gives each image (its per-image buffers must not carry over)."""
    cfg = LineConfig()
    scenes = [draw([(bar(*EDGES[0], 12.0), 200)], seed=1),
              draw([(bar(*EDGES[1], 9.0), 30), (bar(*EDGES[2], 15.0), 220)], seed=2)[40:300, 100:900],
              draw([(bar(*EDGES[2], 6.0), 180)], background=90, seed=3)]
    for image in scenes + scenes[::-1]:
        fresh = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, cfg.lsd_scale).detect(image)[0]
        fresh = np.zeros((0, 4)) if fresh is None else fresh.reshape(-1, 4)
        got = detect_lsd(image, cfg)
        assert len(got) == len(fresh) > 0
        np.testing.assert_array_equal(got, fresh.astype(np.float64) + 0.5 * (1.0 / cfg.lsd_scale - 1.0))
