"""Sparser lidars: HDL-64E scans resampled to 32 / 16 beams by elevation ring, and depth priors that
still get made on them because the patches follow the ring spacing."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from plvo.config import SystemConfig
from plvo.data.dataset import SourceOptions
from plvo.data.kitti import KittiOdometry
from plvo.data.registry import open_dataset
from plvo.depth.density import ring_spacing_px
from plvo.depth.extract import extract_depth
from plvo.depth.projection import project_scan
from plvo.errors import PlvoError
from plvo.features.extract import extract_features
from plvo.lidar.beams import HDL64E_ELEVATIONS_DEG, beam_rings, elevation_deg, resample_beams
from plvo_eval.kiss import timed_scan_reader


@pytest.fixture(scope="module")
def frames(synth_seq):
    ds = KittiOdometry(synth_seq, "00", frames=slice(0, 20, 4))
    return [ds[i] for i in range(len(ds))]


def test_rings_from_elevation_on_the_town(frames):
    scan = frames[0].scan
    rings = beam_rings(scan)
    counts = np.bincount(rings, minlength=64)
    assert (counts > 0).all()  # every HDL-64E beam is found
    # the town's beams are exact: each return lies within a tenth of the beam spacing of its ring's elevation
    assert np.abs(elevation_deg(scan) - HDL64E_ELEVATIONS_DEG[rings]).max() < 0.05
    for n in (16, 32):
        thin = resample_beams(scan, n)
        kept = np.unique(beam_rings(thin))
        np.testing.assert_array_equal(kept, np.arange(0, 64, 64 // n))
        assert len(thin) == pytest.approx(len(scan) * n / 64, rel=0.05)
    assert resample_beams(scan, 64) is scan
    with pytest.raises(PlvoError, match="beams 24: must be one of 8, 16, 32, 64"):
        resample_beams(scan, 24)


def test_real_kitti_rings_with_elevation_offset(kitti_root):
    f = KittiOdometry(kitti_root, "04", frames=slice(0, 1))[0]
    thin = resample_beams(f.scan, 16, f.calib.lidar_elevation_offset_deg)
    assert 0.2 < len(thin) / len(f.scan) < 0.35  # about a quarter (real beams are not exactly nominal)


def test_ring_spacing_follows_beam_count(frames):
    f, cfg = frames[1], SystemConfig().depth
    spacing = {}
    for n in (16, 32, 64):
        proj = project_scan(resample_beams(f.scan, n), f.calib, cfg.min_depth_m, cfg.max_depth_m, cfg.grid_cell_px,
                            cfg.zbuffer_px)
        spacing[n] = ring_spacing_px(proj)
    assert 4.0 < spacing[64] < 6.0  # the paper's 7 px patch suits this
    assert spacing[32] / spacing[64] == pytest.approx(2.0, rel=0.2)
    assert spacing[16] / spacing[64] == pytest.approx(4.0, rel=0.2)


def _share(frames, n_beams: int, adapt: bool) -> tuple[float, list]:
    cfg = SystemConfig()
    dcfg = replace(cfg.depth, adapt_to_ring_spacing=adapt)
    ok = total = 0
    priors = []
    for f in frames:
        feats = extract_features(f.image, cfg.orb, cfg.lines)
        p = extract_depth(resample_beams(f.scan, n_beams), feats, f.calib, dcfg).priors
        ok, total = ok + int(p.point_valid.sum()), total + len(p.point_valid)
        priors.append(p)
    return ok / total, priors


def test_depth_priors_on_sparse_scans(frames):
    dense, dense_priors = _share(frames, 64, adapt=True)
    same, same_priors = _share(frames, 64, adapt=False)
    assert dense == same  # a dense scan keeps the paper's patches exactly
    for a, b in zip(dense_priors, same_priors):
        np.testing.assert_array_equal(a.point_depth, b.point_depth)
    for n, floor in ((16, 0.7), (32, 0.85)):
        fixed, _ = _share(frames, n, adapt=False)
        adapted, _ = _share(frames, n, adapt=True)
        assert adapted >= floor * dense, (n, adapted, dense)
        assert adapted > fixed + 0.1, (n, adapted, fixed)  # the paper's 7 px patch finds far fewer


def test_beams_option_resamples_any_source(synth_seq):
    ds = open_dataset(synth_seq, "00", frames=slice(0, 3), options=SourceOptions(beams=16))
    full = KittiOdometry(synth_seq, "00", frames=slice(0, 3))
    assert len(ds) == 3 and ds.frame_indices == (0, 1, 2)
    np.testing.assert_allclose(ds.calib.K, full.calib.K)
    assert len(ds[1].scan) == pytest.approx(len(full[1].scan) / 4, rel=0.05)
    again = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(again[1].scan, ds[1].scan)
    # the lidar-only peers read the same thinned scans (they read without decoding the images)
    np.testing.assert_array_equal(timed_scan_reader(ds)(1)[0], ds[1].scan)
    np.testing.assert_array_equal(ds.load_scan(2), ds[2].scan)
