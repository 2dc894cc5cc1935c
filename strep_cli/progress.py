"""Progress of a run on stderr: the CLI's sink (`strep_core.events.Sink`)."""

from __future__ import annotations

import sys
from typing import Any, Literal

ProgressMode = Literal["bar", "lines", "off"]


class ProgressSink:
    """Progress of every stage of a run, on stderr.

    ``bar``: a line per stage (loading, warm start, writing) and a tqdm bar while optimising
    (a terminal, or ``--progress``); ``lines``: one line per stage, the optimisation included,
    no bar (stderr is a file or a pipe); ``off``: nothing (``--quiet``).
    """

    def __init__(self, mode: ProgressMode, method: str) -> None:
        self.mode = mode
        self.bar: Any = None
        self.method = method
        self.unit = ""
        self.optimising = False
        self.counts = "iterations"  # what the method's iterations count (`MethodInfo.counts`)
        self.shown = 0  # the warm start's last progress line, in tenths

    def _stage_progress(self, event: Any) -> None:
        """A long stage's ``done`` of ``total``: a bar, or a line every tenth."""
        if self.mode == "bar":
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=event.total, desc="warm start", unit="step", leave=False, file=sys.stderr)
            self.bar.n = event.done
            self.bar.refresh()
            return
        tenth = 10 * event.done // max(event.total, 1)
        if tenth > self.shown:
            self.shown = tenth
            from strep_core.events import stage_label

            self._line(f"{stage_label(event.stage)}: {event.done}/{event.total} steps")

    def _line(self, text: str) -> None:
        if self.bar is not None:
            from tqdm import tqdm

            tqdm.write(f"{self.method}: {text}", file=sys.stderr)
        else:
            print(f"{self.method}: {text}", file=sys.stderr, flush=True)

    def emit(self, event: Any) -> None:
        if self.mode == "off":
            return
        from strep_core.events import stage_label

        if event.kind == "stage" and event.done is not None:
            self._stage_progress(event)
        elif event.kind == "stage":
            self.close()
            self._line(f"{stage_label(event.stage)} ...")
        elif event.kind == "start":
            self.close()
            self.method, self.unit, self.total, self.optimising = (
                event.method,
                event.unit,
                event.total_iterations,
                False,
            )
            from strep_core.methods import available

            info = available().get(event.method)
            self.counts = info.counts if info is not None else "iterations"
        elif event.kind == "iteration":
            ate = f"ATE {event.ate:.4g} {self.unit}" if event.ate is not None else None
            if event.iteration == 0:  # the starting poses: after the warm start, if any
                self._line(f"starting poses: {ate}" if ate else "starting poses ready")
            if not self.optimising and event.iteration < event.total:
                self.optimising = True
                doing = "optimising" if self.counts == "iterations" else "registering"
                self._line(f"{doing} ({event.total} {self.counts}) ...")
                if self.mode == "bar":
                    from tqdm import tqdm

                    self.bar = tqdm(total=event.total, desc=self.method, unit="it", leave=False, file=sys.stderr)
            if self.bar is not None:
                self.bar.n = event.iteration
                post = {k: f"{v:.4g}" for k, v in event.losses.items() if k == "total"}
                if event.ate is not None:
                    post["ate"] = f"{event.ate:.3g}"
                self.bar.set_postfix(post, refresh=False)
                self.bar.refresh()
        elif event.kind == "result":
            self.close()
            ate = event.metrics.get("ate")
            done = f"registered: ATE {ate:.4g} {self.unit}" if isinstance(ate, (int, float)) else "registered"
            self._line(f"{done}, {event.wall_seconds:.1f} s")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
