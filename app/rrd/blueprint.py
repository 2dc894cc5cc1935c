"""The recordings' layout: timelines, colours and the default blueprint a ``.rrd`` opens in."""

from __future__ import annotations

import rerun.blueprint as rrb

APPLICATION_ID = "strep-studio"
ITERATION = "iteration"  # timeline: the event's iteration (the result's count at the end)
ELAPSED = "elapsed"  # timeline: seconds since the run started
GT_COLOR = (150, 150, 150)
TRAJECTORY_COLORS = [(230, 80, 40), (40, 120, 230), (40, 170, 90), (170, 70, 200), (220, 170, 30)]


def default_blueprint(keys: list[str]) -> rrb.Blueprint:
    """3D view of ``world`` (map snapshots hidden) beside loss, ATE and summary views."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="Registration",
                origin="world",
                overrides={f"world/{k}/map": rrb.EntityBehavior(visible=False) for k in keys},
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="Loss", origin="metrics", contents=[f"+ metrics/{k}/loss/**" for k in keys] or "$origin/**"
                ),
                rrb.TimeSeriesView(name="ATE", origin="metrics", contents=[f"+ metrics/{k}/ate" for k in keys]),
                rrb.TextDocumentView(name="Summary", origin="summary"),
                row_shares=[2, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
