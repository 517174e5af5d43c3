"""Per-twin figures: path, zones, objects, movers seen, camera height above the ground, ORB/LSD counts and the
share of LSD segments on cast-shadow edges (every STEP-th frame).

Usage: python scripts/twin_stats.py TWIN_ROOT [STEP]     (prints a Markdown table)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

from plvo.config import LineConfig, OrbConfig
from plvo.features.lines import detect_lines, detect_lsd
from plvo.features.points import detect_orb

sys.path.insert(0, str(Path(__file__).resolve().parent))
from twin_vs_kitti import on_shadow_edge  # noqa: E402


def main(argv: list[str]) -> int:
    root = Path(argv[0])
    step = int(argv[1]) if len(argv) > 1 else 10
    print("| twin | frames | path m | zones (m) | objects | movers (in view) | cam0 above ground m (min / max) "
          "| ORB | LSD raw | lines >= 50 px | LSD raw on shadow edges | lines on shadow edges |")
    print("| --- | ---: | ---: | --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    for seq_dir in sorted((root / "sequences").iterdir()):
        if seq_dir.name.startswith("."):
            continue
        scene = json.loads((seq_dir / "gt" / "scene.json").read_text())
        n = scene["follow"]["n_frames"]
        gt = np.loadtxt(root / "poses" / f"{seq_dir.name}.txt").reshape(-1, 3, 4)[:, :, 3]
        length = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
        zones = ", ".join(f"{k} {v:.0f}" for k, v in scene["world"]["zones_m"].items() if v > 0)
        boxes = [json.loads(line) for line in (seq_dir / "gt" / "boxes.jsonl").read_text().splitlines()]
        seen = {m["id"] for b in boxes for m in b["movers"] if m["pixels"] > 0}
        h = np.array(scene["camera"]["height_above_ground_m"])
        orb, raw, lines, sh_raw, sh_lines = [], [], [], [], []
        for i in range(0, n, step):
            img = cv2.imread(str(seq_dir / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
            edges = cv2.imread(str(seq_dir / "gt" / "shadow_edges" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            r = detect_lsd(img, LineConfig())
            seg = detect_lines(img, LineConfig()).segments
            orb.append(len(detect_orb(img, OrbConfig()).xy))
            raw.append(len(r))
            lines.append(len(seg))
            sh_raw.append(on_shadow_edge(r, edges).sum())
            sh_lines.append(on_shadow_edge(seg, edges).sum())
        print(f"| {seq_dir.name} | {n} | {length:.0f} | {zones} | {sum(scene['world']['objects'].values())} | "
              f"{len(scene['traffic'])} ({len(seen)}) | {h.min():.2f} / {h.max():.2f} | {np.mean(orb):.0f} | "
              f"{np.mean(raw):.0f} | {np.mean(lines):.0f} | {np.sum(sh_raw) / max(np.sum(raw), 1):.1%} | "
              f"{np.sum(sh_lines) / max(np.sum(lines), 1):.1%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
