"""The viewer's shared control panel: the run picker, follow live, replay, ground truth,
point size, and a status line.

One presenter: every tab sees the same controls (per-tab state would need per-client scenes
and multiply the traffic). Callbacks run on viser's threads and only change the viewer's
state (through the `ViewerServer` methods named below); the pusher thread writes the
controls back with `Controls.apply`.
"""

from __future__ import annotations

from typing import Any, Protocol

import viser

from app.viewer.panel import Job, show

NO_RUN = "(no runs yet)"


class Target(Protocol):
    """What the controls change: the `ViewerServer`'s state (named here, not imported, so the
    viewer, its pusher and the controls import one another in one direction only)."""

    def _pick_group(self, group: str) -> None: ...

    def _play(self, playing: bool) -> None: ...

    def set_replay(
        self, *, live: bool | None = None, iteration: int | None = None, playing: bool | None = None
    ) -> None: ...

    def set_display(self, *, show_gt: bool | None = None, point_scale: float | None = None) -> None: ...


def status_text(ui: dict[str, Any]) -> str:
    """The status line: what the shown run is doing and what the replay controls will do."""
    if not ui["groups"]:
        return "no runs yet"
    if ui["playing"]:
        return f"replaying: iteration {ui['replay_it']}"
    if not ui["live"]:
        return f"paused at iteration {ui['replay_it']}"
    if ui.get("finished"):
        return "finished: Play replays it, the Iteration slider steps through it"
    return "following the run live"


def _set_value(handle: Any, value: Any) -> None:
    """Set a GUI input from the server (its callbacks see ``client is None`` and ignore it)."""
    handle.value = value


class Controls:
    """The control panel of ``viewer`` (docked on the right, beside the scene)."""

    def __init__(self, gui: viser.GuiApi, viewer: Target) -> None:
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.main_panel.dock_right()  # beside the scene, not over it (the camera frames the rest)
        self.run = gui.add_dropdown("Run", (NO_RUN,), initial_value=NO_RUN)
        self.live = gui.add_checkbox("Follow live", initial_value=True)
        self.play = gui.add_button_group("Replay", ("Play", "Pause"))
        self.iteration = gui.add_slider("Iteration", min=0, max=1, step=1, initial_value=0)
        self.ground_truth = gui.add_checkbox("Ground truth", initial_value=True)
        self.point_size = gui.add_slider("Point size", min=0.1, max=5.0, step=0.1, initial_value=1.0)
        self.status = gui.add_markdown("")
        #: the run picker's entries (as shown) -> group id, as last applied
        self.run_options: dict[str, str] = {}
        #: the handles by name, for embedding and tests
        self.handles: dict[str, Any] = {
            "run": self.run,
            "live": self.live,
            "replay": self.play,
            "iteration": self.iteration,
            "ground_truth": self.ground_truth,
            "point_size": self.point_size,
        }

        @self.run.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is None:
                return
            group = self.run_options.get(self.run.value)
            if group is not None:
                viewer._pick_group(group)

        @self.live.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                viewer.set_replay(live=self.live.value, playing=False if self.live.value else None)

        @self.play.on_click
        def _(ev: viser.GuiEvent) -> None:
            viewer._play(self.play.value == "Play")

        @self.iteration.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                viewer.set_replay(iteration=int(self.iteration.value), playing=False)

        @self.ground_truth.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                viewer.set_display(show_gt=bool(self.ground_truth.value))

        @self.point_size.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                viewer.set_display(point_scale=float(self.point_size.value))

    def apply(self, ui: dict[str, Any], jobs: list[Job]) -> None:
        """Write the view state ``ui`` (a copy taken under the viewer's lock) into the controls
        and the jobs' visibility, point sizes and ground-truth lines."""
        selected = ui["selected"]
        options: dict[str, str] = {}
        for group, members in ui["groups"].items():
            title = ui["titles"].get(group) or " vs ".join(ui["labels"].get(m, m) for m in members)
            text = title if group == members[0] and len(members) == 1 and title == group else f"{title} [{group}]"
            while text in options:
                text += "'"
            options[text] = group
        self.run_options = options
        shown = [t for t, g in options.items() if g == selected]
        if options:
            self.run.options = tuple(options)
            if shown:
                _set_value(self.run, shown[0])
        else:
            self.run.options = (NO_RUN,)
            _set_value(self.run, NO_RUN)
        for job in jobs:
            if job.built:
                show(job, visible=job.group == selected, show_gt=ui["show_gt"], point_scale=ui["point_scale"])
        _set_value(self.live, ui["live"])
        self.iteration.max = max(int(ui["max_it"]), 1)
        shown_it = ui["latest_it"] if ui["live"] else ui["replay_it"]  # never a value left from another run
        _set_value(self.iteration, min(int(shown_it), self.iteration.max))
        _set_value(self.ground_truth, ui["show_gt"])
        _set_value(self.point_size, ui["point_scale"])
        self.status.content = status_text(ui)

    def follow(self, max_it: int, latest: int) -> None:
        """Live: the iteration slider follows the newest iteration (totals become known after
        the job appears)."""
        self.iteration.max = max(int(max_it), 1)
        _set_value(self.iteration, min(latest, self.iteration.max))
