"""One job's panel in the viser scene: its nodes, how a snapshot moves them, its text.

Nodes of a job (``<job>`` is its key)::

    /jobs/<job>                  frame: the job's panel, offset along +x (side by side)
    /jobs/<job>/label            label: "<label>" and the current iteration / ATE
    /jobs/<job>/est              frame: display anchor G_0 inv(T_0) (identity without GT)
    /jobs/<job>/est/f<k>         point cloud of frame k (float32, strided), posed by T_k
                                 (sequences of more than ``frame_nodes_max`` frames instead
                                 get one cloud /jobs/<job>/map re-sent at each push)
    /jobs/<job>/trajectory       line segments: estimated positions
    /jobs/<job>/poses            batched axes: at most ``max_pose_markers`` poses
    /jobs/<job>/gt               line segments: ground-truth trajectory (when known)

Everything here runs on the viewer's pusher thread, the only one that calls viser after
start-up. What the job *is* (stage, history, metrics) is its `RunState`, built by
`strep_core.runstate.apply`; a `Job` adds only what has been drawn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.viewer.scene import (
    SequenceScene,
    bbox,
    display_anchor,
    label_position,
    poses_to_matrices,
    rotations_to_wxyz,
    union_bbox,
)
from strep_core.runstate import RunState, Snapshot, stage_line
from strep_core.runview import figure

GT_COLOR = (120, 120, 120)
TRAJECTORY_COLORS = [(230, 80, 40), (40, 120, 230), (40, 170, 90), (170, 70, 200), (220, 170, 30)]


@dataclass
class Job:
    """A job shown by the viewer: its identity, its `RunState`, and what the pusher drew."""

    job_id: str
    label: str
    group: str
    key: str
    scene: SequenceScene
    state: RunState
    index: int
    # pusher-owned
    built: bool = False
    shown: Snapshot | None = None
    shown_rev: int = -1
    last_push: float = -math.inf
    nodes: dict[str, Any] = field(default_factory=dict)
    frame_nodes: list[Any] = field(default_factory=list)
    chart: Any = None
    chart_series: tuple[str, ...] = ()
    chart_exponent: int = 0  # loss curves are drawn in units of 10**chart_exponent
    chart_pushed: float = -math.inf
    box: tuple[np.ndarray, np.ndarray] | None = None
    shown_box: tuple[np.ndarray, np.ndarray] | None = None  # the estimated map as last pushed (framing)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def root(self) -> str:
        return f"/jobs/{self.key}"

    def box_of(self) -> tuple[np.ndarray, np.ndarray]:
        """The panel's extent: the ground-truth map and the estimated map as last laid out
        (a unit box before either is known)."""
        box = union_bbox(self.scene.gt_bbox(), self.box)
        return box if box is not None else (np.zeros(3), np.ones(3))

    def point_size(self, point_scale: float) -> float:
        return 0.3 * self.scene.marker_scale() * point_scale


FOLDER_ORDER = 1_000_000.0  # past every control's automatic order


def build(
    server: viser.ViserServer,
    job: Job,
    *,
    visible: bool,
    point_scale: float,
    show_gt: bool,
    frame_nodes_max: int,
) -> None:
    """Create the job's nodes and its GUI folder (hidden until its first snapshot)."""
    scene, sc, root = server.scene, job.scene, job.root
    marker = sc.marker_scale()
    job.nodes[root] = scene.add_frame(root, show_axes=False, visible=visible)
    job.nodes[f"{root}/label"] = scene.add_label(
        f"{root}/label", job.label, position=tuple(label_position(job.box_of())), anchor="bottom-center"
    )
    job.nodes[f"{root}/est"] = scene.add_frame(f"{root}/est", show_axes=False, visible=False)
    size = job.point_size(point_scale)
    if len(sc) <= frame_nodes_max:
        job.frame_nodes = [
            scene.add_point_cloud(f"{root}/est/f{k}", pts, color, point_size=size, precision="float32")
            for k, (pts, color) in enumerate(zip(sc.frames, sc.colors, strict=True))
        ]
    else:  # one fused cloud, in display coordinates; only its points change
        job.nodes[f"{root}/map"] = scene.add_point_cloud(
            f"{root}/map",
            np.concatenate(sc.frames),
            sc.point_colors(),
            point_size=size,
            precision="float32",
            visible=False,
        )
    color = TRAJECTORY_COLORS[job.index % len(TRAJECTORY_COLORS)]
    job.nodes[f"{root}/trajectory"] = scene.add_line_segments(
        f"{root}/trajectory",
        np.zeros((1, 2, 3), np.float32),
        color,
        thickness=2.0,
        thickness_units="screen",
        visible=False,
    )
    job.nodes[f"{root}/poses"] = scene.add_batched_axes(
        f"{root}/poses",
        np.tile([1.0, 0.0, 0.0, 0.0], (1, 1)),
        np.zeros((1, 3)),
        axes_length=2.0 * marker,
        axes_radius=0.15 * marker,
        visible=False,
    )
    if sc.ground_truth is not None:
        pos = sc.ground_truth[:, :3, 3]
        job.nodes[f"{root}/gt"] = scene.add_line_segments(
            f"{root}/gt",
            np.stack([pos[:-1], pos[1:]], 1),
            GT_COLOR,
            thickness=1.5,
            thickness_units="screen",
            visible=show_gt,
        )
    # below the controls, in the group's order (the page's), whichever job was built first
    with server.gui.add_folder(job.label, visible=visible, order=FOLDER_ORDER + job.index) as folder:
        job.nodes["gui/folder"] = folder
        job.nodes["gui/text"] = server.gui.add_markdown(f"**{job.label}**: waiting for events")
    job.built = True


def destroy(job: Job) -> None:
    """Remove the job's nodes, children first, then its GUI."""
    for node in job.frame_nodes:
        node.remove()
    scene_nodes = [n for n in job.nodes if not n.startswith("gui/")]
    for name in sorted(scene_nodes, key=lambda n: -n.count("/")):  # children first
        job.nodes[name].remove()
    for name in ("gui/chart", "gui/text", "gui/folder"):
        handle = job.nodes.get(name)
        if handle is not None:
            handle.remove()
    job.nodes.clear()
    job.frame_nodes.clear()


def show(job: Job, *, visible: bool, show_gt: bool, point_scale: float) -> None:
    """Apply the shared display settings to a built job."""
    job.nodes[job.root].visible = visible
    job.nodes["gui/folder"].visible = visible
    gt = job.nodes.get(f"{job.root}/gt")
    if gt is not None:
        gt.visible = show_gt
    size = job.point_size(point_scale)
    for node in job.frame_nodes:
        node.point_size = size
    if f"{job.root}/map" in job.nodes:
        job.nodes[f"{job.root}/map"].point_size = size


def place(job: Job, offset: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> None:
    """Move the panel to ``offset`` and its label above ``box``."""
    job.offset = offset
    if job.built:
        job.nodes[job.root].position = offset
        job.nodes[f"{job.root}/label"].position = label_position(box)


def draw(job: Job, snap: Snapshot, *, max_pose_markers: int) -> bool:
    """Move the job's frames, trajectory and pose markers to ``snap``'s poses.

    Returns True when the panel's extent changed enough to lay the panels out again.
    """
    if snap.poses is None:
        return False
    root = job.root
    est = poses_to_matrices(snap.poses)
    anchor = display_anchor(est, job.scene.ground_truth)
    shown = anchor[None] @ est
    est_node = job.nodes[f"{root}/est"]
    est_node.wxyz = rotations_to_wxyz(anchor[:3, :3])
    est_node.position = anchor[:3, 3]
    est_node.visible = True
    if job.frame_nodes:
        wxyz = rotations_to_wxyz(est[:, :3, :3])
        for node, q, t in zip(job.frame_nodes, wxyz, est[:, :3, 3], strict=True):
            node.wxyz = q
            node.position = t
    else:
        cloud = job.nodes[f"{root}/map"]
        cloud.points = job.scene.fuse(shown)
        cloud.visible = True
    pos = shown[:, :3, 3]
    traj = job.nodes[f"{root}/trajectory"]
    traj.points = np.stack([pos[:-1], pos[1:]], 1).astype(np.float32)
    traj.visible = True
    step = max(1, math.ceil(len(pos) / max_pose_markers))
    axes = job.nodes[f"{root}/poses"]
    axes.batched_wxyzs = rotations_to_wxyz(shown[::step, :3, :3]).astype(np.float32)
    axes.batched_positions = pos[::step].astype(np.float32)
    axes.visible = True
    box = bbox(job.scene.fuse(shown, max_points=4096))
    job.shown_box = box  # from scratch the estimate spreads beyond the ground truth's box
    # the panel's extent follows the estimate too (a failing run's map can be twice the
    # ground truth's), with hysteresis so that re-layouts stay rare
    size, old = box[1][:2] - box[0][:2], None if job.box is None else job.box[1][:2] - job.box[0][:2]
    if old is None or not np.all((0.7 * old <= size) & (size <= 1.05 * old)):
        job.box = box
        return True
    return False


#: the result's figures on the status line: metrics key -> (label, unit: "seq" the sequence's)
RESULT_FIGURES = {"ate": ("ATE", "seq"), "point_l2": ("point L2", "seq"), "wall_seconds": ("time", "s")}


def result_line(metrics: dict[str, Any], unit: str) -> str:
    """``"ATE 134 px, point L2 206 px, time 1099 s"``: labelled, 3 significant digits, units."""
    parts = []
    for key, (label, kind) in RESULT_FIGURES.items():
        v = metrics.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            parts.append(f"{label} {figure(v)} {unit if kind == 'seq' else kind}".rstrip())
    return ", ".join(parts) or "no figures"


def update_text(job: Job, snap: Snapshot | None) -> None:
    """The job's figures in its GUI folder and on its label in the scene."""
    state = job.state
    lines = [f"**{job.label}** ({state.method or '?'})"]
    if snap is not None:
        total = f"/{state.total}" if state.total else ""
        lines.append(f"iteration {snap.iteration}{total}, {snap.elapsed:.1f} s")
        terms = {k: v for k, v in snap.losses.items() if v != 0.0}  # a term that is off reports 0
        if terms:
            lines.append("loss: " + ", ".join(f"{k} {v:.3g}" for k, v in terms.items()))
        if snap.ate is not None:
            lines.append(f"ATE {snap.ate:.3g} {job.scene.unit}")
    stage = stage_line(state.stage, snap, start_ate=state.start_ate, unit=job.scene.unit, finished=state.finished)
    if stage:
        lines.append(stage)
    if state.finished:
        lines.append("finished: " + result_line(state.metrics, job.scene.unit))
    job.nodes["gui/text"].content = "  \n".join(lines)
    label = job.label if snap is None else f"{job.label}  it {snap.iteration}"
    if snap is not None and snap.ate is not None:
        label += f"  ATE {snap.ate:.3g}"
    job.nodes[f"{job.root}/label"].text = label
