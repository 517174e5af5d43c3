"""Share of features with a depth prior, and their error against the town's true depth, at 16/32/64 beams.

usage: PYTHONPATH=. .venv/bin/python scripts/beams_depth_share.py ROOT SEQ A:B:S
(every S-th frame of A..B-1; the point depth error is against the town's gt/depth when the sequence has it)
"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from plvo.config import SystemConfig
from plvo.data.kitti import KittiOdometry
from plvo.depth.extract import extract_depth
from plvo.features.extract import extract_features
from plvo.lidar.beams import resample_beams

root, seq, frames = sys.argv[1], sys.argv[2], slice(*map(int, sys.argv[3].split(":")))
cfg = SystemConfig()
ds = KittiOdometry(root, seq, frames=frames)
gt_dir = Path(root) / "sequences" / seq / "gt" / "depth"
feats = [extract_features(ds[i].image, cfg.orb, cfg.lines) for i in range(len(ds))]
for adapt in (False, True):
    dcfg = replace(cfg.depth, adapt_to_ring_spacing=adapt)
    for beams in (16, 32, 64):
        pts = lines = npts = nlines = 0
        errs = []
        for i in range(len(ds)):
            f = ds[i]
            scan = resample_beams(f.scan, beams, f.calib.lidar_elevation_offset_deg)
            pri = extract_depth(scan, feats[i], f.calib, dcfg).priors
            ok = pri.point_valid
            pts += int(ok.sum())
            npts += len(ok)
            lines += int(pri.line_valid.sum())
            nlines += len(pri.line_valid)
            gt_file = gt_dir / f"{f.index:06d}.npy"
            if gt_file.is_file() and ok.any():
                gt = np.load(gt_file)
                uv = np.round(feats[i].keypoints[ok]).astype(int)
                true = gt[uv[:, 1], uv[:, 0]]
                good = np.isfinite(true) & (true > 0)
                errs.append(np.abs(pri.point_depth[ok][good] - true[good]) / true[good])
        e = np.concatenate(errs) if errs else np.array([np.nan])
        print(f"adapt={'on ' if adapt else 'off'} {beams:2d} beams: points with a depth prior {pts / npts:5.1%} "
              f"({pts}/{npts}), lines {lines / nlines:5.1%} ({lines}/{nlines}); point depth vs truth: median "
              f"{np.median(e):.2%}, 90th pct {np.percentile(e, 90):.2%}")
