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

        if event.kind == "stage":
            self._line(f"{stage_label(event.stage)} ...")
        elif event.kind == "start":
            self.close()
            self.method, self.unit, self.total, self.optimising = (
                event.method,
                event.unit,
                event.total_iterations,
                False,
            )
        elif event.kind == "iteration":
            ate = f"ATE {event.ate:.4g} {self.unit}" if event.ate is not None else None
            if event.iteration == 0:  # the starting poses: after the warm start, if any
                self._line(f"starting poses: {ate}" if ate else "starting poses ready")
            if not self.optimising and event.iteration < event.total:
                self.optimising = True
                self._line(f"optimising ({event.total} iterations) ...")
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
