"""What a lidar's scans look like, ring by ring: the figures the twins' lidar realism is set from and checked against.

For each source (a folder of KITTI .bin scans: the real KITTI frames or a twin's), over its scans:
  returns      returns per ring and sweep, against the ring's firings (360 deg over its azimuth step)
  gaps         isolated misses (1-3 firings without a return between two returns, so no sky or range limit) per
               return, and their rate against the reflectance of the return before the gap
  noise        range noise: the robust sigma of the second difference of range along a ring between neighbouring
               firings (4-25 m), / sqrt(6); on smooth surfaces this is the range noise itself
  rough        the share of returns whose second difference exceeds 0.1 m (edges, and returns scattered in foliage)
  road         the road around the car (4-25 m ahead or behind, within 2.5 m of the car's line, near a robust plane):
               each ring's median height above the plane fitted to all rings; their spread is what the beams'
               elevation and range biases leave
A source is DIR[:ORDER[:OFFSET]]: ORDER how rings are recovered, "kitti" (ring by ring, a ring starting where the
azimuth crosses 0 upwards: KITTI's files), "sweep" (ring by ring in sweep order: realistic twins) or "elevation"
(the nearest HDL-64E beam: ideal twins); OFFSET the vertical-angle error (deg) taken out first, as readers do
(0.205 for KITTI and realistic twins, 0 for ideal twins).

Usage: python scripts/lidar_realism_stats.py OUT_DIR NAME=SOURCE [NAME=SOURCE ...] [--frames A:B]
  e.g. real04=../shared/data/kitti/sequences/04/velodyne:kitti:0.205
Writes OUT_DIR/lidar_stats.json, lidar_stats.md and lidar_rings.png.

       python scripts/lidar_realism_stats.py --ego-table DIR [DIR ...]
prints the recording car's shadow in KITTI's scans (twin.lidars.EGO_RETURN_NINTHS): per ring from 42 and 10 deg of
azimuth, the share of firings that return, the highest over the folders given (KITTI files, rings by "kitti"
order), in ninths, 9 where 85 % or more.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np

from plvo.lidar.beams import beam_rings
from plvo.lidar.scan import raise_elevation

N_BEAMS = 64
REFL_BINS = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.6, 1.01])


def rings_of(scan: np.ndarray, order: str, offset: float) -> np.ndarray:
    az = np.arctan2(scan[:, 1], scan[:, 0])
    if order == "kitti":
        start = np.concatenate([[False], (az[:-1] < 0) & (az[1:] >= 0)])
    elif order == "sweep":
        start = np.concatenate([[False], np.diff(az) > np.pi])
    elif order == "elevation":
        return beam_rings(scan, offset)
    else:
        raise SystemExit(f"order {order!r}: kitti, sweep or elevation")
    return np.cumsum(start)


def scan_stats(scan: np.ndarray, order: str, offset: float) -> dict:
    ring = rings_of(scan, order, offset)
    pts = raise_elevation(scan, offset)
    az = np.arctan2(pts[:, 1], pts[:, 0])
    rng = np.linalg.norm(pts[:, :3], axis=1)
    refl = scan[:, 3]
    out = {"n": len(scan), "rings": int(ring.max()) + 1, "count": np.bincount(ring, minlength=N_BEAMS)[:N_BEAMS]}
    d2s, rough_n, rough_k = [], 0, 0
    gap_refl, all_refl = [], []
    firing = []
    for r in range(min(N_BEAMS, int(ring.max()) + 1)):
        k = np.flatnonzero(ring == r)
        if len(k) < 20:
            continue
        da = np.abs(np.angle(np.exp(1j * np.diff(az[k]))))
        step = np.median(da)
        firing.append(step)
        gaps = np.rint(da / step).astype(int) - 1  # firings without a return between neighbours
        isolated = (gaps >= 1) & (gaps <= 3)
        gap_refl.append(np.repeat(refl[k[:-1]][isolated], gaps[isolated]))
        all_refl.append(refl[k[:-1]][gaps <= 3])
        # second difference over runs of neighbouring firings
        nb = (gaps[:-1] == 0) & (gaps[1:] == 0)
        rr = rng[k]
        d2 = rr[:-2] - 2 * rr[1:-1] + rr[2:]
        near = (rr[1:-1] > 4.0) & (rr[1:-1] < 25.0) & nb
        d2s.append(d2[near])
        rough_n += int(near.sum())
        rough_k += int((np.abs(d2[near]) > 0.1).sum())
    out["step_deg"] = float(np.degrees(np.median(firing)))
    out["d2"] = np.concatenate(d2s) if d2s else np.zeros(0)
    out["rough"] = (rough_k, rough_n)
    out["gap_refl"] = np.concatenate(gap_refl) if gap_refl else np.zeros(0)
    out["all_refl"] = np.concatenate(all_refl) if all_refl else np.zeros(0)
    out["road"] = road_rings(pts, ring)
    return out


def road_rings(pts: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """(64,) each ring's median height (m) above a robust plane through the road around the car (NaN: no road)."""
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    d = np.hypot(x, y)
    cand = (d > 4.0) & (d < 25.0) & (np.abs(y) < 2.5) & (z < -1.2) & (z > -2.2)
    P, rr = pts[cand, :3].astype(np.float64), ring[cand]
    if len(P) < 100:
        return np.full(N_BEAMS, np.nan)
    keep = np.ones(len(P), bool)
    for _ in range(5):
        A = np.column_stack([P[keep, 0], P[keep, 1], np.ones(int(keep.sum()))])
        coef = np.linalg.lstsq(A, P[keep, 2], rcond=None)[0]
        res = P[:, 2] - (coef[0] * P[:, 0] + coef[1] * P[:, 1] + coef[2])
        keep = np.abs(res) < max(0.05, 3.0 * 1.4826 * np.median(np.abs(res[keep])))
    out = np.full(N_BEAMS, np.nan)
    for r in range(N_BEAMS):
        m = keep & (rr == r)
        if m.sum() >= 20:
            out[r] = np.median(res[m])
    return out


def source_stats(spec: str, frames: tuple[int, int] | None) -> dict:
    parts = spec.split(":")
    folder, order = Path(parts[0]), parts[1] if len(parts) > 1 else "kitti"
    offset = float(parts[2]) if len(parts) > 2 else 0.0
    files = sorted(folder.glob("*.bin"))
    if frames is not None:
        files = files[frames[0]:frames[1]]
    if not files:
        raise SystemExit(f"{folder}: no .bin scans")
    stats = [scan_stats(np.fromfile(f, np.float32).reshape(-1, 4), order, offset) for f in files]
    counts = np.mean([s["count"] for s in stats], axis=0)
    step = float(np.median([s["step_deg"] for s in stats]))
    firings = 360.0 / step
    d2 = np.concatenate([s["d2"] for s in stats])
    mad = np.median(np.abs(d2 - np.median(d2)))
    rough = np.sum([s["rough"] for s in stats], axis=0)
    gap = np.concatenate([s["gap_refl"] for s in stats])
    allr = np.concatenate([s["all_refl"] for s in stats])
    hg, _ = np.histogram(gap, REFL_BINS)
    ha, _ = np.histogram(allr, REFL_BINS)
    road = np.array([s["road"] for s in stats])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # rings that never see the road: NaN
        ring_median = np.nanmedian(road, axis=0)
    ok = np.isfinite(ring_median)
    return {
        "source": spec, "scans": len(files), "returns_per_scan": float(np.mean([s["n"] for s in stats])),
        "rings": int(np.median([s["rings"] for s in stats])), "azimuth_step_deg": step, "firings_per_ring": firings,
        "returns_per_ring": counts.round(1).tolist(),
        "return_rate_per_ring": (counts / firings).round(4).tolist(),
        "isolated_misses_per_return": float(len(gap) / max(len(allr), 1)),
        "miss_rate_by_reflectance": {f"{lo:.2f}-{hi:.2f}": (round(float(g / a), 4) if a else None)
                                     for lo, hi, g, a in zip(REFL_BINS[:-1], REFL_BINS[1:], hg, ha)},
        "returns_by_reflectance": {f"{lo:.2f}-{hi:.2f}": int(a)
                                   for lo, hi, a in zip(REFL_BINS[:-1], REFL_BINS[1:], ha)},
        "range_noise_m": float(1.4826 * mad / np.sqrt(6.0)),
        "rough_share": float(rough[0] / max(rough[1], 1)),
        "road_ring_offset_m": [None if not np.isfinite(v) else round(float(v), 4) for v in ring_median],
        "road_ring_offset_rms_m": float(np.sqrt(np.mean(ring_median[ok] ** 2))) if ok.any() else None,
        "road_rings": int(ok.sum()),
    }


def figures(out: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    for name, r in results.items():
        ax[0].plot(r["return_rate_per_ring"], label=name)
        mids = 0.5 * (REFL_BINS[:-1] + REFL_BINS[1:])
        rate = [np.nan if v is None else v for v in r["miss_rate_by_reflectance"].values()]
        ax[1].plot(mids, rate, "o-", label=name)
        ax[2].plot([np.nan if v is None else 100 * v for v in r["road_ring_offset_m"]], "o-", ms=3, label=name)
    ax[0].set(xlabel="ring (0: top beam)", ylabel="returns / firings", title="return rate per ring")
    ax[1].set(xlabel="reflectance of the return before", ylabel="isolated misses per return",
              title="misses against reflectance", yscale="log")
    ax[2].set(xlabel="ring", ylabel="cm", title="road: each ring's median height above the plane")
    for a in ax:
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "lidar_rings.png", dpi=90)
    plt.close(fig)


def ego_table(folders: list[str]) -> list[str]:
    best = np.zeros((N_BEAMS, 36))
    for folder in folders:
        bins = np.zeros((N_BEAMS, 36))
        for f in sorted(Path(folder).glob("*.bin")):
            scan = np.fromfile(f, np.float32).reshape(-1, 4)
            ring = rings_of(scan, "kitti", 0.0)
            b = ((np.degrees(np.arctan2(scan[:, 1], scan[:, 0])) + 180.0) // 10.0).astype(int) % 36
            ok = ring < N_BEAMS
            np.add.at(bins, (ring[ok], b[ok]), 1)
        best = np.maximum(best, np.clip(bins / np.percentile(bins[40:], 90), 0.0, 1.0))
    best = np.where(best >= 0.85, 1.0, best)
    return ["".join(str(int(round(9 * x))) for x in best[r]) for r in range(42, N_BEAMS)]


def main(argv: list[str]) -> int:
    if argv[:1] == ["--ego-table"]:
        print("\n".join(f'    "{row}",' for row in ego_table(argv[1:])))
        return 0
    frames = None
    if "--frames" in argv:
        k = argv.index("--frames")
        a, b = argv[k + 1].split(":")
        frames = (int(a), int(b))
        argv = argv[:k] + argv[k + 2:]
    if len(argv) < 2:
        print(__doc__)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for item in argv[1:]:
        name, spec = item.split("=", 1)
        results[name] = source_stats(spec, frames)
    (out / "lidar_stats.json").write_text(json.dumps(results, indent=1))
    lines = ["| source | scans | returns/scan | az step deg | isolated misses/return | range noise cm | rough % | "
             "road ring offset rms cm (rings) |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, r in results.items():
        rms = r["road_ring_offset_rms_m"]
        lines.append(f"| {name} | {r['scans']} | {r['returns_per_scan']:.0f} | {r['azimuth_step_deg']:.4f} | "
                     f"{r['isolated_misses_per_return']:.4f} | {100 * r['range_noise_m']:.2f} | "
                     f"{100 * r['rough_share']:.2f} | {'-' if rms is None else f'{100 * rms:.2f}'} "
                     f"({r['road_rings']}) |")
    (out / "lidar_stats.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    figures(out, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
