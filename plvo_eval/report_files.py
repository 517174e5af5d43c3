"""An evaluation's files: report.json and report.md (plvo_eval.report) and the figures (plvo_eval.plots)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from plvo.atomic import write_text_atomic
from plvo_eval import provenance
from plvo_eval.plots import write_plots
from plvo_eval.report import Report, report_json, report_markdown


def write_report(report: Report, out_dir: str | os.PathLike[str], plots: bool = True,
                 started: dict[str, Any] | None = None) -> dict[str, Path]:
    """Write report.md, report.json and (plots) the PNG figures under out_dir; returns name -> path.

    started: plvo_eval.provenance.start() of the evaluation (its load then); default: made now. report.json carries it,
    finished now, as "provenance"."""
    out = Path(out_dir)
    data = report_json(report)
    data["provenance"] = provenance.finish(started if started is not None else provenance.start())
    paths = {"json": out / "report.json", "markdown": out / "report.md"}
    write_text_atomic(paths["json"], json.dumps(data, indent=1, allow_nan=False) + "\n")
    write_text_atomic(paths["markdown"], report_markdown(report, data))
    if plots:
        paths.update(write_plots(report, out / "plots"))
    return paths
