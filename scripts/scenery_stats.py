"""How hard a clip's scenery is for the camera and the lidar, measured alike on real KITTI frames and on a twin's:
ORB and line counts, how often consecutive frames' ORB matches are ambiguous, the match rate, and the lidar's
foliage signature. What plvo_synth.twin.scenery_realism's densities are calibrated with.

Usage: python scripts/scenery_stats.py NAME=FOLDER [NAME=FOLDER ...] [--frames A:B] [--json OUT.json]
e.g.   python scripts/scenery_stats.py real04=../shared/data/kitti/sequences/04 \
           real0009=../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_0009_sync \
           twin04=TWINS/sequences/04 --frames 0:51
A FOLDER is an odometry sequence (image_0/, velodyne/) or a raw drive (image_00/data/, velodyne_points/data/);
frames are taken in name order. Prints one Markdown table of per-frame means (the lidar's also by region).

The measures (plvo.features with the default config, no motion prediction):
- ORB keypoints at the default cap (1000, which every KITTI-like frame reaches), and FAST corners at ORB's
  threshold (FAST_THRESHOLD, full resolution, non-maximum suppressed), which no cap hides; LSD: raw segments and
  the repaired lines >= 50 px the system uses.
- ORB matches between consecutive frames: each previous descriptor's nearest and second-nearest current descriptor
  (Hamming, over the whole frame); a candidate is a mutual nearest pair within the matcher's point_max_hamming.
  ambiguous: the share of candidates whose second-nearest distance is within 1 / point_ratio of the nearest (the
  matcher's Lowe test rejects them); match rate: the accepted candidates over the previous frame's keypoints
  (what match_points returns); F-inliers: the share of accepted matches a fundamental matrix keeps (RANSAC, 1 px).
- lidar: returns are put in rings (KITTI's files are stored ring by ring, each a turn of increasing azimuth;
  a twin's are stored column by column and are put in rings by elevation) and sorted by azimuth; a return is
  isolated when its range differs by more than ISOLATED_M from both ring neighbours (each within MAX_GAP_DEG of
  azimuth): the signature of foliage, where neighbouring beams land at scattered depths in a crown. The share is
  over the returns with both neighbours; by region: left / right (azimuth 30-150 deg either side), ahead (within
  30 deg), and high (more than HIGH_M above the sensor: crowns, facades).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from plvo.config import LineConfig, MatchingConfig, OrbConfig
from plvo.features.extract import extract_features
from plvo.features.matching import hamming_matrix

FAST_THRESHOLD = 20  # OrbConfig.fast_threshold
ISOLATED_M = 0.5
MAX_GAP_DEG = 0.6
HIGH_M = 0.3  # above the sensor (1.73 m over the road on KITTI's car): 2 m over the road
MIN_RING_WRAPS = 32  # a file with this many azimuth wrap-arounds is stored ring by ring
# HDL-64E nominal elevations (as plvo_synth.sensors), the start for a twin's ring assignment
NOMINAL_ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


# ---------------------------------------------------------------------------------------------- reading


def clip_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """An odometry sequence or a raw drive folder -> its images and scans, in name order."""
    for img_dir, velo_dir in (("image_0", "velodyne"), ("image_00/data", "velodyne_points/data")):
        if (folder / img_dir).is_dir():
            return sorted((folder / img_dir).glob("*.png")), sorted((folder / velo_dir).glob("*.bin"))
    raise SystemExit(f"{folder}: neither an odometry sequence (image_0/) nor a raw drive (image_00/data/)")


def read_scan(path: Path) -> np.ndarray:
    raw = np.fromfile(path, np.float32)
    if raw.size % 4:
        raise SystemExit(f"{path}: {raw.size} floats, not a multiple of 4 (x, y, z, reflectance)")
    return raw.reshape(-1, 4)


# ---------------------------------------------------------------------------------------------- camera


def orb_pair_stats(prev, cur, cfg: MatchingConfig) -> dict:
    """Candidates, ambiguous share, match rate and F-inlier share of prev -> cur (FeatureSets)."""
    n_prev = len(prev.keypoints)
    if n_prev == 0 or len(cur.keypoints) < 2:
        return {"ambiguous": np.nan, "match_rate": 0.0, "f_inliers": np.nan}
    dist = hamming_matrix(prev.descriptors, cur.descriptors)
    part = np.partition(dist, 1, axis=1)
    d1, d2 = part[:, 0], part[:, 1]
    best = dist.argmin(axis=1)
    mutual = dist.argmin(axis=0)[best] == np.arange(n_prev)
    cand = np.flatnonzero(mutual & (d1 <= cfg.point_max_hamming))
    if not len(cand):
        return {"ambiguous": np.nan, "match_rate": 0.0, "f_inliers": np.nan}
    ambiguous = d1[cand] >= cfg.point_ratio * d2[cand]
    acc = cand[~ambiguous]
    f_in = np.nan
    if len(acc) >= 8:
        _, mask = cv2.findFundamentalMat(prev.keypoints[acc].astype(np.float64),
                                         cur.keypoints[best[acc]].astype(np.float64), cv2.FM_RANSAC, 1.0, 0.999)
        f_in = float(mask.mean()) if mask is not None else np.nan
    return {"ambiguous": float(ambiguous.mean()), "match_rate": len(acc) / n_prev, "f_inliers": f_in}


def camera_stats(images: list[Path]) -> dict[str, list[float]]:
    orb_cfg, line_cfg, match_cfg = OrbConfig(), LineConfig(), MatchingConfig()
    fast = cv2.FastFeatureDetector_create(FAST_THRESHOLD, True)
    out: dict[str, list[float]] = {k: [] for k in ("orb", "fast", "lsd_raw", "lines", "ambiguous",
                                                   "match_rate", "f_inliers")}
    prev = None
    for path in images:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise SystemExit(f"{path}: not a readable image")
        fs = extract_features(image, orb_cfg, line_cfg)
        out["orb"].append(len(fs.keypoints))
        out["fast"].append(len(fast.detect(image)))
        out["lsd_raw"].append(len(fs.raw_segments))
        out["lines"].append(len(fs.segments))
        if prev is not None:
            for k, v in orb_pair_stats(prev, fs, match_cfg).items():
                out[k].append(v)
        prev = fs
    return out


# ---------------------------------------------------------------------------------------------- lidar


def rings(points: np.ndarray) -> np.ndarray:
    """(N,4) scan -> (N,) ring index: from the storage order when the file is stored ring by ring (KITTI), else
    the nearest of the elevations refitted to the scan (a twin's files go column by column)."""
    az = np.arctan2(points[:, 1], points[:, 0])
    wraps = np.flatnonzero(np.diff(az) < -np.pi)
    if len(wraps) >= MIN_RING_WRAPS:
        ring = np.zeros(len(points), np.int64)
        ring[wraps + 1] = 1
        return np.cumsum(ring)
    el = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    centres = NOMINAL_ELEVATIONS_DEG.copy()
    for _ in range(3):  # refit: a rig's per-beam angle offsets move the rings off the nominal elevations
        ring = np.abs(el[:, None] - centres[None, :]).argmin(axis=1)
        sums = np.bincount(ring, el, minlength=len(centres))
        counts = np.bincount(ring, minlength=len(centres))
        centres = np.where(counts > 0, sums / np.maximum(counts, 1), centres)
    return ring


def isolated_returns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,4) scan -> (N,) whether each return is isolated in its ring, (N,) whether it has both neighbours."""
    ring = rings(points)
    az = np.arctan2(points[:, 1], points[:, 0])
    r = np.linalg.norm(points[:, :3], axis=1)
    order = np.lexsort((az, ring))
    ro, azo, rr = ring[order], az[order], r[order]
    gap = np.radians(MAX_GAP_DEG)
    same_prev = np.zeros(len(r), bool)
    same_prev[1:] = (ro[1:] == ro[:-1]) & (azo[1:] - azo[:-1] < gap)
    same_next = np.zeros(len(r), bool)
    same_next[:-1] = same_prev[1:]
    jump_prev = np.zeros(len(r), bool)
    jump_prev[1:] = np.abs(rr[1:] - rr[:-1]) > ISOLATED_M
    jump_next = np.zeros(len(r), bool)
    jump_next[:-1] = jump_prev[1:]
    both = same_prev & same_next
    iso, has = np.zeros(len(r), bool), np.zeros(len(r), bool)
    iso[order] = both & jump_prev & jump_next
    has[order] = both
    return iso, has


LIDAR_REGIONS = ("all", "left", "right", "ahead", "high")


def lidar_stats(scans: list[Path]) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {f"iso_{k}": [] for k in LIDAR_REGIONS}
    out["returns"] = []
    for path in scans:
        p = read_scan(path)
        iso, has = isolated_returns(p)
        az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
        region = {"all": np.ones(len(p), bool), "left": (az > 30) & (az < 150), "right": (az < -30) & (az > -150),
                  "ahead": np.abs(az) <= 30, "high": p[:, 2] > HIGH_M}
        for k, m in region.items():
            sel = m & has
            out[f"iso_{k}"].append(float(iso[sel].mean()) if sel.any() else np.nan)
        out["returns"].append(len(p))
    return out


# ---------------------------------------------------------------------------------------------- report


COLUMNS = (("orb", "ORB", "{:.0f}"), ("fast", "FAST corners", "{:.0f}"),
           ("lsd_raw", "LSD raw", "{:.0f}"), ("lines", "lines >= 50 px", "{:.0f}"),
           ("ambiguous", "ORB ambiguous", "{:.1%}"), ("match_rate", "ORB match rate", "{:.1%}"),
           ("f_inliers", "F-inliers", "{:.1%}"), ("returns", "returns", "{:.0f}"),
           *((f"iso_{k}", f"isolated {k}", "{:.2%}") for k in LIDAR_REGIONS))


def clip_stats(folder: Path, frames: tuple[int, int] | None) -> dict[str, float]:
    images, scans = clip_files(folder)
    if frames is not None:
        images, scans = images[frames[0]:frames[1]], scans[frames[0]:frames[1]]
    if len(images) < 2 or not scans:
        raise SystemExit(f"{folder}: {len(images)} images and {len(scans)} scans in range, need 2 and 1")
    per_frame = {**camera_stats(images), **lidar_stats(scans)}
    return {k: float(np.nanmean(v)) for k, v in per_frame.items()}


def parse_frames(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise SystemExit(f"--frames {text!r}: expected A:B") from None
    if not 0 <= a < b:
        raise SystemExit(f"--frames {text!r}: expected 0 <= A < B")
    return a, b


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clips", nargs="+", help="NAME=FOLDER")
    ap.add_argument("--frames", help="A:B, the frames of each clip (default: all)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args(argv)
    frames = parse_frames(args.frames)
    results = {}
    for spec in args.clips:
        name, sep, folder = spec.partition("=")
        if not sep:
            raise SystemExit(f"{spec!r}: expected NAME=FOLDER")
        results[name] = clip_stats(Path(folder), frames)
    print("| clip | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("| --- |" + " ---: |" * len(COLUMNS))
    for name, res in results.items():
        print(f"| {name} | " + " | ".join(fmt.format(res[key]) for key, _, fmt in COLUMNS) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
