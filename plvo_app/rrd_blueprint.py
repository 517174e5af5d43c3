"""plvo's default Rerun blueprint: the layout a recording opens with, in the Rerun viewer and in `plvo view`."""

from __future__ import annotations

import rerun.blueprint as rrb


def blueprint() -> rrb.Blueprint:
    """3D world on the left; the camera image with overlays, time series, the decision log and the list of the
    detail frames on the right.

    The camera panel is the image's pinhole space: it holds the full image with its overlays on detail frames and,
    under them, every keyframe's small image (world/camera/image/keyframe, scaled up to the same pixels), so that
    it is never empty between detail frames (latest-at: the last keyframe's image until the next)."""
    plots = rrb.Tabs(
        rrb.TimeSeriesView(name="tracking", origin="metrics/tracking"),
        rrb.TimeSeriesView(name="timings (ms)", origin="metrics/time"),
        rrb.TimeSeriesView(name="back end", origin="metrics/backend"),
        rrb.TimeSeriesView(name="other counts", origin="metrics", contents=[
            "+ $origin/**", "- /metrics/time/**", "- /metrics/tracking/**", "- /metrics/backend/**"]),
    )
    notes = rrb.Tabs(rrb.TextLogView(name="log", origin="log"),
                     rrb.TextDocumentView(name="full detail: where", origin="detail"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="3D world", origin="world"),
            rrb.Vertical(rrb.Spatial2DView(name="camera", origin="world/camera/image"), plots, notes,
                         row_shares=[3, 2, 1]),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
