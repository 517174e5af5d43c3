"""A twin frame beside a real KITTI frame, with ORB and LSD counts (plvo.features) and, for the twin, the share of
LSD segments lying on cast-shadow edges (the twin's gt/shadow_edges).

Usage: python scripts/twin_vs_kitti.py TWIN_ROOT SEQ FRAME REAL_IMAGE OUT.png
e.g.   python scripts/twin_vs_kitti.py /tmp/twins 00 50 ../shared/data/kitti/sequences/04/image_0/000000.png \
           docs/twin00_vs_kitti04.png
Prints one Markdown table; writes a half-size side-by-side PNG with the detections drawn.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from plvo.config import LineConfig, OrbConfig
from plvo.features.lines import detect_lines, detect_lsd
from plvo.features.points import detect_orb

ON_EDGE_SHARE = 0.7  # a segment is on a shadow edge when this share of its points is


def on_shadow_edge(segments: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(S,4) segments, (H,W) bool edge mask -> (S,) whether each runs along the mask."""
    out = np.zeros(len(segments), bool)
    h, w = edges.shape
    for k, (x1, y1, x2, y2) in enumerate(segments):
        n = max(2, int(np.hypot(x2 - x1, y2 - y1)))
        s = np.linspace(0.0, 1.0, n)
        x = np.clip(np.rint(x1 + s * (x2 - x1)).astype(int), 0, w - 1)
        y = np.clip(np.rint(y1 + s * (y2 - y1)).astype(int), 0, h - 1)
        out[k] = edges[y, x].mean() >= ON_EDGE_SHARE
    return out


def counts(image: np.ndarray) -> dict:
    orb = detect_orb(image, OrbConfig())
    raw = detect_lsd(image, LineConfig())
    lines = detect_lines(image, LineConfig())
    return {"orb": len(orb.xy), "lsd_raw": len(raw), "lines": len(lines.segments), "xy": orb.xy,
            "raw": raw, "segments": lines.segments}


def draw(image: np.ndarray, c: dict, shadow: np.ndarray | None) -> np.ndarray:
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    for k, (x1, y1, x2, y2) in enumerate(c["segments"]):
        colour = (0, 0, 255) if shadow is not None and shadow[k] else (0, 200, 0)
        cv2.line(out, (int(x1), int(y1)), (int(x2), int(y2)), colour, 2)
    for x, y in c["xy"]:
        cv2.circle(out, (int(x), int(y)), 2, (255, 128, 0), -1)
    return out


def main(argv: list[str]) -> int:
    root, seq, frame, real_path, out_path = Path(argv[0]), argv[1], int(argv[2]), Path(argv[3]), Path(argv[4])
    seq_dir = root / "sequences" / seq
    twin = cv2.imread(str(seq_dir / "image_0" / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)
    edges = cv2.imread(str(seq_dir / "gt" / "shadow_edges" / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
    real = cv2.imread(str(real_path), cv2.IMREAD_GRAYSCALE)
    if twin is None or real is None:
        raise SystemExit(f"cannot read {seq_dir / 'image_0' / f'{frame:06d}.png'} or {real_path}")
    ct, cr = counts(twin), counts(real)
    sh_lines = on_shadow_edge(ct["segments"], edges)
    sh_raw = on_shadow_edge(ct["raw"], edges)
    panel_t = draw(twin, ct, sh_lines)
    panel_r = draw(real, cr, None)
    width = min(panel_t.shape[1], panel_r.shape[1])
    panels = [cv2.resize(p[:, :width], (width // 2, p.shape[0] // 2), interpolation=cv2.INTER_AREA)
              for p in (panel_t, panel_r)]
    for p, text in zip(panels, (f"twin {seq} frame {frame}: ORB {ct['orb']}, LSD {ct['lsd_raw']} raw / {ct['lines']} "
                                 f">= 50 px, {sh_lines.mean():.0%} of those on shadow edges (red)",
                                 f"real KITTI {real_path.parent.parent.name} {real_path.stem}: ORB {cr['orb']}, "
                                 f"LSD {cr['lsd_raw']} raw / {cr['lines']} >= 50 px")):
        cv2.putText(p, text, (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 255, 255), 1, cv2.LINE_AA)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), np.vstack(panels))
    print("| image | ORB keypoints | LSD segments (raw) | line segments >= 50 px | on shadow edges (raw / >= 50 px) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    print(f"| twin {seq} frame {frame} | {ct['orb']} | {ct['lsd_raw']} | {ct['lines']} | "
          f"{sh_raw.mean():.1%} / {sh_lines.mean():.1%} |")
    print(f"| real KITTI {real_path.parent.parent.name} {real_path.stem} | {cr['orb']} | {cr['lsd_raw']} | "
          f"{cr['lines']} | (unknown) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
