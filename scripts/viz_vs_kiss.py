"""plvo-viz's own frames a second (its timings.json) beside KISS-ICP's on the same scans, each in a fresh process.

usage: .venv/bin/python scripts/viz_vs_kiss.py ROOT SEQ ROUNDS [OUT.json]
Each round runs `plvo-viz --root ROOT --seq SEQ --no-serve` (the defaults: worker processes, recording on) into a
temporary folder, then KISS-ICP over the same scans read from disk (plvo_eval.bench.kiss_fps) in a new Python
process; prints each pair and the median of the ratios, and writes them as JSON when OUT.json is given.
"""
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

KISS = ("import sys; from plvo.data.registry import open_dataset; from plvo_eval.bench import kiss_fps; "
        "print(kiss_fps(open_dataset(sys.argv[1], sys.argv[2])))")


def main(root: str, seq: str, rounds: int, out: str | None) -> None:
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    pairs = []
    for r in range(rounds):
        with tempfile.TemporaryDirectory(prefix="plvo-vs-kiss-") as tmp:
            subprocess.run([str(bin_dir / "plvo-viz"), "--root", root, "--seq", seq, "--no-serve",
                            "--rrd", f"{tmp}/run.rrd", "--out", f"{tmp}/run"], check=True, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            plvo = json.loads(Path(f"{tmp}/run/timings.json").read_text())["frames_per_second"]
        kiss = float(subprocess.run([sys.executable, "-c", KISS, root, seq], check=True, env=env,
                                    capture_output=True, text=True).stdout.split()[-1])
        pairs.append({"plvo_viz_fps": round(plvo, 3), "kiss_icp_fps": round(kiss, 3), "ratio": round(plvo / kiss, 3)})
        print(f"round {r + 1}: plvo-viz {plvo:.2f} frames/s, KISS-ICP {kiss:.2f}, ratio {plvo / kiss:.3f}", flush=True)
    summary = {"root": root, "sequence": seq, "pairs": pairs,
               "median_plvo_viz_fps": statistics.median(p["plvo_viz_fps"] for p in pairs),
               "median_kiss_icp_fps": statistics.median(p["kiss_icp_fps"] for p in pairs),
               "median_ratio": statistics.median(p["ratio"] for p in pairs)}
    print(f"median ratio {summary['median_ratio']:.3f} (plvo-viz {summary['median_plvo_viz_fps']:.2f}, "
          f"KISS-ICP {summary['median_kiss_icp_fps']:.2f} frames/s)")
    if out:
        Path(out).write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__.strip().splitlines()[2])
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] if len(sys.argv) == 5 else None)
