"""Image statistics of a camera clip, the same measures on real KITTI frames and on a twin's: noise against
brightness, edge sharpness, vignetting, exposure steps, saturation, and ORB / line counts and frame-to-frame match
rates (plvo.features). What plvo_synth.twin.camera_effects' settings are measured with.

Usage: python scripts/camera_stats.py NAME=FOLDER [NAME=FOLDER ...] [--frames A:B] [--json OUT.json]
e.g.   python scripts/camera_stats.py real04=../shared/data/kitti/sequences/04/image_0 \
           real0009=../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_0009_sync/image_00/data \
           twin04=TWINS/sequences/04/image_0 --frames 0:51
Each folder's PNGs are read in name order; the principal point and focal length come from the folder's calib
(odometry calib.txt P0, or a raw drive's calib_cam_to_cam.txt P_rect_00), else the image centre and 721 px.
Prints one Markdown table a measure.

The measures:
- noise: Immerkaer's estimate (sigma = sqrt(pi/2) / 6 * mean |I * N|, N the 3x3 Laplacian difference mask) on
  8x8 blocks; per brightness bin the 10th percentile over the clip's blocks (a lower envelope: textured blocks
  read high). It reads the noise's high frequencies, so noise made spatially correlated by a rectification's
  resampling reads lower than its per-pixel sigma, on real and twin frames alike.
- sharpness: the edge spread sigma (px) of an erf fitted to the mean perpendicular profile of each straight LSD
  edge (>= 30 px, contrast >= 30 grey, unsaturated); the median over the clip. And the share of the image's
  gradient energy above 0.25 cycles/px.
- vignetting and exposure steps: the same surface patch seen in two consecutive frames (LK-tracked, forward-
  backward checked) has brightness ratio g_k V(r2) / V(r1): a robust least-squares fit of one gain g_k per frame
  pair and log V(r) = b1 r^2 + b2 r^4 (r: distance from the principal point over the focal length). V is reported
  at r = 0.3, 0.5, 0.7 and 0.85 (0.85: the image's left and right edges), g_k as frame-to-frame steps.
- the naive vignetting profile: mean grey against r over the clip, over its value at r < 0.1 (scene layout
  confounds it; shown beside the fit).
- features: plvo.features.extract_features with the default config; match rate = unpredicted mutual matches
  (match_points, match_lines) over the previous frame's features, and for points the share of those that a
  fundamental matrix (RANSAC, 1 px) keeps.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import curve_fit
from scipy.special import erf

from plvo.config import LineConfig, MatchingConfig, OrbConfig
from plvo.features.extract import extract_features
from plvo.features.matching import match_lines, match_points

NOISE_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
BLOCK = 8
BRIGHTNESS_BINS = (8, 32, 64, 96, 128, 160, 200, 245)
SATURATED = 250
VIGNETTE_RADII = (0.3, 0.5, 0.7, 0.85)


# ---------------------------------------------------------------------------------------------- reading


def read_clip(folder: Path, frames: tuple[int, int] | None) -> list[np.ndarray]:
    files = sorted(folder.glob("*.png"))
    if frames is not None:
        files = files[frames[0]:frames[1]]
    if not files:
        raise SystemExit(f"{folder}: no PNG frames")
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    bad = [str(f) for f, im in zip(files, images) if im is None]
    if bad:
        raise SystemExit(f"{bad[0]}: cannot read the image")
    return images


def intrinsics(folder: Path, shape: tuple[int, int]) -> tuple[float, float, float]:
    """(f, cx, cy) of the clip's rectified camera 0."""
    folder = folder.resolve()
    drive_day = folder.parents[min(2, len(folder.parents) - 1)]  # a raw drive: DAY/DAY_drive_NNNN_sync/image_00/data
    for calib in (folder.parent / "calib.txt", drive_day / "calib_cam_to_cam.txt"):
        if not calib.exists():
            continue
        for line in calib.read_text().splitlines():
            key, _, values = line.partition(":")
            if key in ("P0", "P_rect_00"):
                p = np.array(values.split(), float).reshape(3, 4)
                return float(p[0, 0]), float(p[0, 2]), float(p[1, 2])
    return 721.0, shape[1] / 2.0, shape[0] / 2.0


# ---------------------------------------------------------------------------------------------- noise


def block_noise(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per 8x8 block: mean grey, Immerkaer sigma, whether any pixel is saturated or black."""
    img = image.astype(np.float64)
    r = np.abs(cv2.filter2D(img, cv2.CV_64F, NOISE_MASK, borderType=cv2.BORDER_REFLECT))[1:-1, 1:-1]
    core = img[1:-1, 1:-1]
    h, w = (core.shape[0] // BLOCK) * BLOCK, (core.shape[1] // BLOCK) * BLOCK

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[:h, :w].reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).swapaxes(1, 2).reshape(-1, BLOCK * BLOCK)

    b_img, b_r = blocks(core), blocks(r)
    sigma = math.sqrt(math.pi / 2.0) / 6.0 * b_r.mean(axis=1)
    clipped = (b_img.max(axis=1) >= SATURATED) | (b_img.min(axis=1) <= 2)
    return b_img.mean(axis=1), sigma, clipped


def noise_table(images: list[np.ndarray]) -> dict:
    means, sigmas = [], []
    for im in images:
        m, s, c = block_noise(im)
        means.append(m[~c])
        sigmas.append(s[~c])
    m, s = np.concatenate(means), np.concatenate(sigmas)
    out = {}
    for lo, hi in zip(BRIGHTNESS_BINS[:-1], BRIGHTNESS_BINS[1:]):
        sel = (m >= lo) & (m < hi)
        out[f"{lo}-{hi}"] = float(np.percentile(s[sel], 10)) if sel.sum() >= 50 else None
    out["all"] = float(np.percentile(s, 10))
    return out


# ---------------------------------------------------------------------------------------------- sharpness


_LSD = None


def _lsd():
    global _LSD
    if _LSD is None:
        _LSD = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    return _LSD


def _esf(s: np.ndarray, a: float, b: float, s0: float, sigma: float) -> np.ndarray:
    return a + b * 0.5 * (1.0 + erf((s - s0) / (math.sqrt(2.0) * sigma)))


def edge_spreads(image: np.ndarray, min_len: float = 30.0, min_contrast: float = 30.0) -> np.ndarray:
    """(E,4): edge spread sigma (px), |cos| of the edge's normal against the image's x axis, and the edge's
    midpoint x, y, for each long, contrasted, unsaturated straight edge of the image."""
    img = image.astype(np.float32)
    seg = _lsd().detect(image)[0]
    if seg is None:
        return np.zeros((0, 4))
    seg = seg.reshape(-1, 4).astype(np.float64)
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    keep = length >= min_len
    offsets = np.arange(-6.0, 6.01, 0.25)
    out = []
    for (x1, y1, x2, y2), L in zip(seg[keep], length[keep]):
        t = np.arange(0.15, 0.85, 1.0 / L)
        ux, uy = (x2 - x1) / L, (y2 - y1) / L
        nx, ny = -uy, ux
        px = x1 + t[:, None] * (x2 - x1) + offsets[None, :] * nx
        py = y1 + t[:, None] * (y2 - y1) + offsets[None, :] * ny
        if px.min() < 0 or py.min() < 0 or px.max() > img.shape[1] - 1 or py.max() > img.shape[0] - 1:
            continue
        prof = cv2.remap(img, px.astype(np.float32), py.astype(np.float32), cv2.INTER_LINEAR)
        if prof.max() >= SATURATED:
            continue
        p = prof.mean(axis=0).astype(np.float64)
        lo, hi = p[:8].mean(), p[-8:].mean()
        if abs(hi - lo) < min_contrast:
            continue
        try:
            (_, _, _, sigma), _ = curve_fit(_esf, offsets, p, p0=(lo, hi - lo, 0.0, 1.0), maxfev=400)
        except (RuntimeError, ValueError):
            continue
        sigma = abs(sigma)
        if 0.2 < sigma < 4.0:
            out.append((sigma, abs(nx), (x1 + x2) / 2.0, (y1 + y2) / 2.0))
    return np.array(out).reshape(-1, 4)


def directional_spreads(edges: np.ndarray, f: float, cx: float) -> dict:
    """Median edge spread of edges across the image's x axis (normal within 30 deg of it: blurred by sideways image
    motion) and along it (normal within 30 deg of y), in the outer columns (|x - cx| / f > 0.45, where driving
    forward moves the image sideways the most) and the central ones (< 0.25)."""
    out = {}
    outer = np.abs(edges[:, 2] - cx) / f > 0.45
    centre = np.abs(edges[:, 2] - cx) / f < 0.25
    across, along = edges[:, 1] > math.cos(math.radians(30)), edges[:, 1] < math.sin(math.radians(30))
    for name, sel in (("outer_across", outer & across), ("outer_along", outer & along),
                      ("centre_across", centre & across), ("centre_along", centre & along)):
        out[name] = float(np.median(edges[sel, 0])) if sel.sum() >= 5 else None
        out[name + "_n"] = int(sel.sum())
    return out


def high_frequency_share(image: np.ndarray) -> float:
    """Share of the gradient energy (power spectrum times |f|^2) above 0.25 cycles/px, over a Hann window."""
    img = image.astype(np.float64)
    img = img - img.mean()
    win = np.outer(np.hanning(img.shape[0]), np.hanning(img.shape[1]))
    p = np.abs(np.fft.rfft2(img * win)) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.rfftfreq(img.shape[1])[None, :]
    f2 = fx * fx + fy * fy
    g = p * f2
    return float(g[f2 > 0.25 ** 2].sum() / g.sum())


# ---------------------------------------------------------------------------------------------- vignetting


def tracked_patches(a: np.ndarray, b: np.ndarray, f: float, cx: float, cy: float):
    """Patches tracked from a to b -> (r_a, r_b, log mean_b - log mean_a) for well-tracked unsaturated patches."""
    pts = cv2.goodFeaturesToTrack(a, 4000, 0.003, 7, blockSize=7)
    if pts is None:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    lk = {"winSize": (15, 15), "maxLevel": 3,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
    nxt, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, **lk)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, nxt, None, **lk)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < 0.3)
    p, q = pts.reshape(-1, 2)[ok], nxt.reshape(-1, 2)[ok]
    h, w = a.shape
    inside = (q[:, 0] > 8) & (q[:, 1] > 8) & (q[:, 0] < w - 9) & (q[:, 1] < h - 9)
    p, q = p[inside], q[inside]
    fa, fb = a.astype(np.float32), b.astype(np.float32)
    ma = np.array([cv2.getRectSubPix(fa, (9, 9), (float(x), float(y))) for x, y in p]).reshape(len(p), -1)
    mb = np.array([cv2.getRectSubPix(fb, (9, 9), (float(x), float(y))) for x, y in q]).reshape(len(q), -1)
    if not len(p):
        return np.zeros(0), np.zeros(0), np.zeros(0)
    good = (ma.max(axis=1) < SATURATED) & (mb.max(axis=1) < SATURATED) & (ma.mean(axis=1) > 15) \
        & (mb.mean(axis=1) > 15)
    ra = np.hypot(p[:, 0] - cx, p[:, 1] - cy) / f
    rb = np.hypot(q[:, 0] - cx, q[:, 1] - cy) / f
    d = np.log(mb.mean(axis=1)) - np.log(ma.mean(axis=1))
    return ra[good], rb[good], d[good]


def fit_vignetting(images: list[np.ndarray], f: float, cx: float, cy: float) -> dict:
    """Robust fit of per-pair log gains and log V(r) = b1 r^2 + b2 r^4 to tracked patches' brightness ratios."""
    rows_pair, ra_all, rb_all, d_all = [], [], [], []
    for k in range(len(images) - 1):
        ra, rb, d = tracked_patches(images[k], images[k + 1], f, cx, cy)
        rows_pair.append(np.full(len(d), k))
        ra_all.append(ra)
        rb_all.append(rb)
        d_all.append(d)
    pair, ra, rb, d = (np.concatenate(x) for x in (rows_pair, ra_all, rb_all, d_all))
    n_pairs = len(images) - 1
    A = np.zeros((len(d), n_pairs + 2))
    A[np.arange(len(d)), pair] = 1.0
    A[:, n_pairs] = rb ** 2 - ra ** 2
    A[:, n_pairs + 1] = rb ** 4 - ra ** 4
    w = np.ones(len(d))
    x = np.zeros(A.shape[1])
    for _ in range(20):  # IRLS with a Cauchy weight (shadows, movers, specular patches are outliers)
        sw = np.sqrt(w)
        x = np.linalg.lstsq(A * sw[:, None], d * sw, rcond=None)[0]
        res = d - A @ x
        scale = 1.4826 * np.median(np.abs(res)) + 1e-6
        w = 1.0 / (1.0 + (res / (2.385 * scale)) ** 2)
    b1, b2 = x[n_pairs], x[n_pairs + 1]
    steps = x[:n_pairs]
    return {"V": {f"{r}": float(np.exp(b1 * r * r + b2 * r ** 4)) for r in VIGNETTE_RADII},
            "b1": float(b1), "b2": float(b2), "patches": int(len(d)),
            "steps_pct": [float(100.0 * (math.exp(s) - 1.0)) for s in steps]}


def naive_profile(images: list[np.ndarray], f: float, cx: float, cy: float) -> dict:
    h, w = images[0].shape
    v, u = np.mgrid[0:h, 0:w]
    r = np.hypot(u - cx, v - cy) / f
    mean = np.mean([im.astype(np.float64) for im in images], axis=0)
    centre = mean[r < 0.1].mean()
    return {f"{x}": float(mean[np.abs(r - x) < 0.03].mean() / centre) for x in VIGNETTE_RADII}


# ---------------------------------------------------------------------------------------------- features


def feature_rates(images: list[np.ndarray]) -> dict:
    orb, line, mcfg = OrbConfig(), LineConfig(), MatchingConfig()
    feats = [extract_features(im, orb, line) for im in images]
    p_rate, p_inl, l_rate = [], [], []
    for a, b in zip(feats[:-1], feats[1:]):
        mp = match_points(a, b, mcfg)
        p_rate.append(len(mp) / max(a.n_points, 1))
        if len(mp) >= 8:
            _, mask = cv2.findFundamentalMat(a.keypoints[mp.pairs[:, 0]], b.keypoints[mp.pairs[:, 1]],
                                             cv2.FM_RANSAC, 1.0, 0.999)
            p_inl.append(float(mask.sum()) / len(mp) if mask is not None else 0.0)
        ml = match_lines(a, b, mcfg)
        l_rate.append(len(ml) / max(a.n_lines, 1))
    return {"orb": float(np.mean([f.n_points for f in feats])), "lines": float(np.mean([f.n_lines for f in feats])),
            "orb_match_rate": float(np.mean(p_rate)), "orb_inlier_share": float(np.mean(p_inl)),
            "line_match_rate": float(np.mean(l_rate))}


# ---------------------------------------------------------------------------------------------- report


def clip_stats(folder: Path, frames: tuple[int, int] | None, features: bool = True) -> dict:
    images = read_clip(folder, frames)
    f, cx, cy = intrinsics(folder, images[0].shape)
    stack = np.array(images)
    below = stack[:, int(round(cy)):]
    edges = np.concatenate([edge_spreads(im) for im in images[::5]])
    spreads = edges[:, 0]
    vig = fit_vignetting(images, f, cx, cy)
    means = stack.reshape(len(images), -1).mean(axis=1)
    out = {
        "frames": len(images), "size": list(images[0].shape), "f_cx_cy": [f, cx, cy],
        "grey": {"mean": float(stack.mean()), "mean_below_horizon": float(below.mean()),
                 "p50": float(np.median(stack)), "saturated_share": float((stack >= 255).mean())},
        "noise": noise_table(images),
        "sharpness": {"edge_sigma_median": float(np.median(spreads)) if len(spreads) else None,
                      "edges": int(len(spreads)),
                      "directional": directional_spreads(edges, f, cx),
                      "hf_share": float(np.mean([high_frequency_share(im) for im in images[::5]]))},
        "vignetting": vig,
        "vignetting_naive": naive_profile(images, f, cx, cy),
        "mean_steps_pct": [float(100.0 * (b / a - 1.0)) for a, b in zip(means[:-1], means[1:])],
    }
    if features:
        out["features"] = feature_rates(images)
    return out


def _steps_summary(steps: list[float]) -> str:
    a = np.abs(np.array(steps))
    return f"{np.median(a):.2f} / {np.percentile(a, 90):.2f} / {a.max():.2f}"


def _pair(d: dict, a: str, b: str) -> str:
    return " / ".join("-" if d[k] is None else f"{d[k]:.2f}" for k in (a, b)) + f" ({d[a + '_n']} / {d[b + '_n']})"


def print_tables(stats: dict[str, dict]) -> None:
    names = list(stats)
    bins = [f"{lo}-{hi}" for lo, hi in zip(BRIGHTNESS_BINS[:-1], BRIGHTNESS_BINS[1:])]
    print("| noise sigma (grey, 10th pct of 8x8 blocks) | " + " | ".join(bins) + " | all |")
    print("| --- |" + " ---: |" * (len(bins) + 1))
    for n in names:
        row = [stats[n]["noise"][b] for b in bins] + [stats[n]["noise"]["all"]]
        print(f"| {n} | " + " | ".join("-" if v is None else f"{v:.2f}" for v in row) + " |")
    print()
    print("| clip | mean grey | below horizon | median | saturated | edge sigma px (edges) | HF share | "
          "V(0.3) | V(0.5) | V(0.7) | V(0.85) | naive V(0.5 / 0.85) | exposure steps % (median / p90 / max) | "
          "mean-grey steps % (median / p90 / max) |")
    print("| --- |" + " ---: |" * 14)
    for n in names:
        s = stats[n]
        v, nv, sh = s["vignetting"]["V"], s["vignetting_naive"], s["sharpness"]
        print(f"| {n} | {s['grey']['mean']:.1f} | {s['grey']['mean_below_horizon']:.1f} | {s['grey']['p50']:.0f} | "
              f"{s['grey']['saturated_share']:.1%} | {sh['edge_sigma_median']:.2f} ({sh['edges']}) | "
              f"{sh['hf_share']:.3f} | "
              + " | ".join(f"{v[str(r)]:.3f}" for r in VIGNETTE_RADII)
              + f" | {nv['0.5']:.2f} / {nv['0.85']:.2f} | {_steps_summary(s['vignetting']['steps_pct'])} | "
              f"{_steps_summary(s['mean_steps_pct'])} |")
    print()
    print("| clip | edge sigma px, outer columns: across x / along x (edges) | central columns: across x / along x |")
    print("| --- | ---: | ---: |")
    for n in names:
        d = stats[n]["sharpness"]["directional"]
        print(f"| {n} | {_pair(d, 'outer_across', 'outer_along')} | {_pair(d, 'centre_across', 'centre_along')} |")
    if all("features" in s for s in stats.values()):
        print()
        print("| clip | ORB | lines | ORB match rate | ORB F-inlier share | line match rate |")
        print("| --- | ---: | ---: | ---: | ---: | ---: |")
        for n in names:
            f = stats[n]["features"]
            print(f"| {n} | {f['orb']:.0f} | {f['lines']:.1f} | {f['orb_match_rate']:.1%} | "
                  f"{f['orb_inlier_share']:.1%} | {f['line_match_rate']:.1%} |")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clips", nargs="+", help="NAME=FOLDER of PNG frames")
    ap.add_argument("--frames", default=None, help="A:B, the frames of each folder (in name order)")
    ap.add_argument("--json", default=None, help="also write every figure to this file")
    ap.add_argument("--no-features", action="store_true", help="skip the feature counts and match rates")
    args = ap.parse_args(argv)
    frames = None
    if args.frames:
        a, b = args.frames.split(":")
        frames = (int(a), int(b))
    stats = {}
    for clip in args.clips:
        name, _, folder = clip.partition("=")
        if not folder:
            raise SystemExit(f"{clip!r}: expected NAME=FOLDER")
        stats[name] = clip_stats(Path(folder), frames, not args.no_features)
    print_tables(stats)
    if args.json:
        Path(args.json).write_text(json.dumps(stats, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
