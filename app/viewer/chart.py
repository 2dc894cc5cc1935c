"""A job's uPlot chart in its GUI folder: the loss terms and the ATE against iterations.

Pusher thread only. The curves come from the job's `RunState` history; a loss term that is
off (weight 0) has no curve.
"""

from __future__ import annotations

import threading

import numpy as np
import viser

from app.viewer.panel import Job

CURVE_COLORS = ["#e6502a", "#2878e6", "#28aa5a", "#aa46c8", "#dcaa1e", "#555555"]


def loss_exponent(curves: list[np.ndarray]) -> int:
    """Power of ten in which to draw loss curves: ``e`` with the largest finite ``|value|`` in
    ``[10**e, 10**(e+1))`` when it lies outside ``[0.01, 1000)`` (uPlot's axis labels show
    three decimals: a Chamfer loss of 1e-4 reads as 0), else 0."""
    v = np.abs(np.concatenate([np.ravel(c) for c in curves])) if curves else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0 or v.max() <= 0:
        return 0
    e = int(np.floor(np.log10(v.max())))
    return e if e < -2 or e > 2 else 0


def series_width(name: str) -> float:
    """The total loss is drawn first and wider: a term equal to it (the only one on) lies on
    top of it, and the total still shows at its edges instead of hiding under it."""
    return 5.0 if name == "loss/total" else 1.5


def update_chart(gui: viser.GuiApi, job: Job, lock: threading.RLock) -> None:
    """Redraw ``job``'s chart (new data in place, or a new chart when its series changed).

    ``lock`` guards the job's history, which event intake appends to from other threads.
    """
    with lock:
        curves = job.state.history.curves()
    if not curves:
        return
    names = tuple(sorted(curves, key=lambda n: (n == "ate", n != "loss/total", n)))
    xs = np.unique(np.concatenate([curves[n][0] for n in names]))
    # one x axis for all series: rows where a series has no value repeat its previous value
    data = [xs]
    for n in names:
        x, y = curves[n]
        idx = np.clip(np.searchsorted(x, xs, side="right") - 1, 0, len(x) - 1)
        data.append(y[idx])
    same = job.chart is not None and job.chart_series == names
    if not same:  # the loss unit is chosen once per chart, so its axis label stays put
        job.chart_exponent = loss_exponent([d for n, d in zip(names, data[1:], strict=True) if n != "ate"])
    unit = 10.0**-job.chart_exponent
    data = [data[0]] + [d if n == "ate" else d * unit for n, d in zip(names, data[1:], strict=True)]
    if same:
        job.chart.data = tuple(data)
        return
    if job.chart is not None:
        job.chart.remove()
    series = [viser.uplot.Series(label="iteration")]
    for i, n in enumerate(names):
        series.append(
            viser.uplot.Series(
                label=n.removeprefix("loss/"),
                stroke=CURVE_COLORS[i % len(CURVE_COLORS)],
                width=series_width(n),
                scale="ate" if n == "ate" else "loss",
            )
        )
    axes = [viser.uplot.Axis()]
    if any(n != "ate" for n in names):
        e = job.chart_exponent
        axes.append(viser.uplot.Axis(scale="loss", label=f"loss (x 1e{e})" if e else "loss"))
    if "ate" in names:
        axes.append(viser.uplot.Axis(scale="ate", side=1, label=f"ATE ({job.scene.unit})"))
    with job.nodes["gui/folder"]:
        job.chart = gui.add_uplot(
            data=tuple(data),
            series=tuple(series),
            scales={"x": viser.uplot.Scale(time=False, auto=True), "loss": {"auto": True}, "ate": {"auto": True}},
            axes=tuple(axes),
            aspect=1.6,
        )
    job.nodes["gui/chart"] = job.chart
    job.chart_series = names
