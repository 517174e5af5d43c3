"""plvo's default Rerun blueprint: the layout a recording opens with, in the Rerun viewer and in `plvo view`."""

from __future__ import annotations

import rerun.blueprint as rrb


def blueprint() -> rrb.Blueprint:
    """3D world on the left; the camera image with overlays, time series and the decision log on the right."""
    plots = rrb.Tabs(
        rrb.TimeSeriesView(name="tracking", origin="metrics/tracking"),
        rrb.TimeSeriesView(name="timings (ms)", origin="metrics/time"),
        rrb.TimeSeriesView(name="back end", origin="metrics/backend"),
        rrb.TimeSeriesView(name="other counts", origin="metrics", contents=[
            "+ $origin/**", "- /metrics/time/**", "- /metrics/tracking/**", "- /metrics/backend/**"]),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="3D world", origin="world"),
            rrb.Vertical(rrb.Spatial2DView(name="camera", origin="world/camera/image"), plots,
                         rrb.TextLogView(name="log", origin="log"), row_shares=[3, 2, 1]),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
