"""The README's real-clip figures are what the commands its result files give produce: each clip run again with
`plvo eval run` as docs/results/real_clips_0af3d75/README.md says, every figure of the README's rows compared to two
decimals, within the last shown digit or 1.5 % of the figure, whichever is larger: the last bits of the floating
point kernels move them (on AVX2 kernels, `make test-bits`, the raw drive's 40 m figure for plvo came out 2.59 where
this machine's AVX-512 ones give the README's 2.57: 0.8 %, the largest change seen). Reads ../shared/data and skips
with a reason where the clips are absent."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from plvo_app.cli import main

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
CLIPS = {
    # README row prefix -> (root, sequence)
    "real KITTI 04, frames 0-50": (DATA / "kitti", "04"),
    "raw drive 2011_09_26_drive_0009, frames 0-50": (DATA / "kitti_raw", "2011_09_26_drive_0009"),
}
TRIPLE = re.compile(r"(\d+\.\d+)\*{0,2} / \*{0,2}(\d+\.\d+)\*{0,2} / \*{0,2}(\d+\.\d+)")


def readme_rows(prefix: str) -> tuple[list[list[float]], list[list[float]]]:
    """The README's two rows of a clip (the devkit reading, then the heading offset taken out) -> per row the 10 /
    20 / 40 m figures of plvo, KISS-ICP and KISS-SLAM."""
    lines = (REPO / "README.md").read_text().splitlines()
    at = next((k for k, line in enumerate(lines) if line.startswith(f"| {prefix}")), None)
    assert at is not None, f"README.md: no results row starting '| {prefix}'"
    rows = []
    for line in lines[at:at + 2]:
        cells = line.split("|")[2:5]
        rows.append([[float(v) for v in TRIPLE.search(cell.replace("%", "")).groups()] for cell in cells])
    return rows[0], rows[1]


def _figures(result: Path) -> tuple[list[float], list[float]]:
    metrics = json.loads(result.read_text())["metrics"]
    plain = [metrics["short"][k]["t_err_pct"] for k in ("10", "20", "40")]
    aligned = [metrics["heading_aligned"]["short"][k]["t_err_pct"] for k in ("10", "20", "40")]
    return plain, aligned


@pytest.mark.parametrize("prefix", list(CLIPS))
def test_the_readmes_real_clip_figures_come_from_its_command(prefix, tmp_path, capsys):
    root, seq = CLIPS[prefix]
    if not root.is_dir():
        pytest.skip(f"{root} not found (see ../shared/data/README.md)")
    out = tmp_path / "eval"
    code = main(["eval", "run", "--root", str(root), "--seq", seq, "--ablations", "full", "--kiss", "--kiss-slam",
                 "--workers", "1", "--no-plots", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    devkit_row, aligned_row = readme_rows(prefix)
    for column, setting in enumerate(("full", "kiss", "kiss_slam")):
        plain, aligned = _figures(out / "runs" / setting / seq / "result.json")
        for shown, measured in ((devkit_row[column], plain), (aligned_row[column], aligned)):
            assert shown == pytest.approx([round(v, 2) for v in measured], rel=0.015, abs=0.0101), (prefix, setting)
