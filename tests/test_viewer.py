"""The viser viewer: scene contents, throttle, comparison layout, replay, lifecycle."""

from __future__ import annotations

import socket
import threading
import time
import urllib.request

import numpy as np
import pytest

from app.core.config import Settings, ViewerSettings
from app.viewer import ViewerServer
from app.viewer.chart import loss_exponent
from app.viewer.scene import display_anchor, poses_to_matrices, rotations_to_wxyz
from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.events import IterationEvent, ListSink, MultiSink, StageEvent, StartEvent, pose_list
from strep_core.runner import load_input, run
from strep_core.runstate import History, Snapshot, stage_line

MAX_POINTS = 8_000
CHART_INTERVAL = ViewerSettings().chart_interval


@pytest.fixture(scope="module")
def seq():
    return load_input("sample:sim2d-small")


@pytest.fixture(scope="module")
def viewer():
    v = ViewerServer(port=0, settings=ViewerSettings(max_points_per_job=MAX_POINTS, max_rate_hz=10.0))
    yield v
    v.close()


@pytest.fixture(scope="module")
def icp_events(seq, viewer):
    """A real icp run, watched live by the viewer (job ``live-icp``)."""
    events = ListSink()
    sink = viewer.sink("live-icp", "icp", seq, select=True)
    run(seq, RunConfig(method="icp"), sink=MultiSink([events, sink]))
    assert viewer.wait_idle(10)
    return events.events


def _frame_pose(viewer: ViewerServer, key: str, k: int) -> tuple[np.ndarray, np.ndarray]:
    node = viewer.scene_node(f"/jobs/{key}/est/f{k}")
    return np.asarray(node.position), np.asarray(node.wxyz)


def _assert_shows(viewer: ViewerServer, key: str, pose_vectors: list[list[float]]) -> None:
    expected = poses_to_matrices(pose_vectors)
    q = rotations_to_wxyz(expected[:, :3, :3])
    for k in (0, len(expected) // 2, len(expected) - 1):
        pos, wxyz = _frame_pose(viewer, key, k)
        np.testing.assert_allclose(pos, expected[k, :3, 3], rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(wxyz, q[k], atol=1e-5)


def test_live_run_builds_the_scene(viewer, seq, icp_events) -> None:
    key = viewer.jobs()["live-icp"]["key"]
    names = set(viewer.node_names())
    root = f"/jobs/{key}"
    assert {root, f"{root}/label", f"{root}/est", f"{root}/trajectory", f"{root}/poses", f"{root}/gt"} <= names
    clouds = [viewer.scene_node(f"{root}/est/f{k}") for k in range(len(seq))]
    assert all(c is not None for c in clouds)
    assert sum(len(c.points) for c in clouds) <= MAX_POINTS
    assert {c.points.dtype for c in clouds} == {np.dtype(np.float32)}
    # the final poses are on screen, the trajectory has K-1 segments, pose markers are bounded
    _assert_shows(viewer, key, icp_events[-1].poses)
    assert viewer.scene_node(f"{root}/trajectory").points.shape == (len(seq) - 1, 2, 3)
    assert len(viewer.scene_node(f"{root}/poses").batched_positions) <= 64
    info = viewer.jobs()["live-icp"]
    assert info["finished"] and info["iteration"] == 64 and info["chart"] == ["ate"]
    assert "icp" in viewer.scene_node(f"{root}/label").text


def test_throttle_keeps_the_latest_state(viewer, seq) -> None:
    gt = g.pose_to_vector(seq.poses)
    rng = np.random.default_rng(0)
    n = 300
    events = [
        IterationEvent(
            iteration=i,
            total=n,
            elapsed=i * 0.01,
            losses={"total": 1.0 / i},
            ate=1.0 / i,
            poses=pose_list(gt + rng.normal(scale=0.5, size=gt.shape)),
        )
        for i in range(1, n + 1)
    ]
    sink = viewer.sink("burst", "burst", seq, select=True)
    sink.emit(
        StartEvent(
            method="fake",
            sequence=seq.name,
            frames=len(seq),
            dims=2,
            unit="px",
            total_iterations=n,
            initial_guess="identity",
        )
    )
    assert viewer.wait_idle(5)
    before = viewer.jobs()["burst"]["pushes"]
    t0 = time.perf_counter()
    for ev in events:
        sink.emit(ev)
    emit_seconds = time.perf_counter() - t0
    assert viewer.wait_idle(5)
    info = viewer.jobs()["burst"]
    # 300 events in a burst -> one push per throttle interval the burst lasted, plus the last
    # state (bounded by the measured burst, so a loaded machine cannot fail it; the producer's
    # own speed is measured by benchmarks/viewer_rate.py)
    assert info["pushes"] - before <= 2 + emit_seconds / viewer.interval
    assert info["shown_iteration"] == n  # ... of the latest state
    _assert_shows(viewer, info["key"], events[-1].poses)
    # paced at ~100 events/s for 1 s: at most ~10 pushes per second
    before = viewer.jobs()["burst"]["pushes"]
    t0 = time.perf_counter()
    for ev in events[:100]:
        sink.emit(ev)
        time.sleep(0.01)
    elapsed = time.perf_counter() - t0
    assert viewer.wait_idle(5)
    pushes = viewer.jobs()["burst"]["pushes"] - before
    assert 1 <= pushes <= elapsed / viewer.interval + 2
    # the history is bounded (300 + 100 snapshots kept within the limit)
    assert viewer.jobs()["burst"]["history"] <= viewer.settings.history_limit


def test_comparison_side_by_side_and_replay(viewer, seq, icp_events) -> None:
    identity = ListSink()
    run(seq, RunConfig(method="identity"), sink=identity)
    stored = [ev.model_dump() for ev in icp_events]  # as the job store keeps them
    viewer.load_job("cmp-icp", "icp", seq, stored, group="cmp", group_title="icp vs identity", select=True)
    viewer.load_job("cmp-id", "identity", seq, identity.events, group="cmp")
    assert viewer.wait_idle(10)
    jobs = viewer.jobs()
    a, b = jobs["cmp-icp"]["key"], jobs["cmp-id"]["key"]
    pa = np.asarray(viewer.scene_node(f"/jobs/{a}").position)
    pb = np.asarray(viewer.scene_node(f"/jobs/{b}").position)
    gt_map = np.concatenate([f @ p[:2, :2].T + p[:2, 2] for f, p in zip(seq.frames, seq.poses, strict=True)])
    width = gt_map[:, 0].max() - gt_map[:, 0].min()
    assert pb[0] - pa[0] > width and pb[1] == pa[1]
    assert viewer.scene_node(f"/jobs/{a}").visible and viewer.scene_node(f"/jobs/{b}").visible
    assert not viewer.scene_node(f"/jobs/{jobs['burst']['key']}").visible  # other runs hidden
    assert viewer.run_options()["icp vs identity [cmp]"] == "cmp"
    # replay: iteration 20 of the stored icp run, then play to the end
    at20 = next(e for e in icp_events if e.kind == "iteration" and e.iteration == 20)
    viewer.set_replay(iteration=20)
    assert viewer.wait_idle(5)
    _assert_shows(viewer, a, at20.poses)
    assert viewer.jobs()["cmp-icp"]["shown_iteration"] == 20
    viewer.set_replay(iteration=0, playing=True)
    deadline = time.monotonic() + 10
    while viewer.replay_state()["playing"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert viewer.wait_idle(5)
    assert viewer.jobs()["cmp-icp"]["shown_iteration"] == 64
    _assert_shows(viewer, a, icp_events[-1].poses)
    viewer.set_replay(live=True)
    assert viewer.wait_idle(5)


def test_clients_get_the_page_and_the_scene(viewer, icp_events) -> None:
    import viser
    import websockets.sync.client as wsc

    with urllib.request.urlopen(viewer.url, timeout=5) as resp:
        assert resp.status == 200
        assert b"<html" in resp.read(2000).lower()
    got = [0, 0]

    def tab(i: int) -> None:  # two browser tabs at once: both receive the scene
        url = f"ws://127.0.0.1:{viewer.port}"
        with wsc.connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            deadline = time.monotonic() + 3
            while time.monotonic() < deadline and got[i] < 100_000:
                try:
                    got[i] += len(ws.recv(timeout=0.5))
                except TimeoutError:
                    break

    threads = [threading.Thread(target=tab, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert min(got) > 50_000  # the replayed scene holds the point clouds (float32)


class _Tab:
    """A minimal browser tab: a viser websocket client that reports a camera and moves controls."""

    def __init__(self, port: int) -> None:
        import viser
        import websockets.sync.client as wsc

        self.ws = wsc.connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self._send(
            {
                "type": "ViewerCameraMessage",
                "wxyz": (1.0, 0.0, 0.0, 0.0),
                "position": (0.0, 0.0, 5.0),
                "fov": 1.0,
                "near": 0.01,
                "far": 1000.0,
                "image_height": 600,
                "image_width": 800,
                "look_at": (0.0, 0.0, 0.0),
                "up_direction": (0.0, 0.0, 1.0),
            }
        )
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _send(self, payload: dict) -> None:
        import msgspec

        self.ws.send(msgspec.msgpack.encode(payload))

    def _drain(self) -> None:
        try:
            while True:
                self.ws.recv()
        except Exception:
            return

    def set(self, handle, value) -> None:
        self._send({"type": "GuiUpdateMessage", "uuid": handle._impl.uuid, "updates": {"value": value}})

    def close(self) -> None:
        self.ws.close()


def _until(predicate, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_gui_controls_from_a_browser_tab(viewer, seq, icp_events) -> None:
    viewer.load_job("gui-icp", "icp", seq, icp_events, select=True)
    assert viewer.wait_idle(5)
    key = viewer.jobs()["gui-icp"]["key"]
    tab = _Tab(viewer.port)
    try:
        assert _until(lambda: len(viewer.server.get_clients()) == 1)
        tab.set(viewer.controls["iteration"], 30)  # dragging the slider leaves live mode
        assert _until(lambda: viewer.replay_state()["iteration"] == 30 and not viewer.replay_state()["live"])
        assert viewer.wait_idle(5) and viewer.jobs()["gui-icp"]["shown_iteration"] == 30
        tab.set(viewer.controls["ground_truth"], False)
        assert _until(lambda: not viewer.replay_state()["show_gt"]) and viewer.wait_idle(5)
        assert not viewer.scene_node(f"/jobs/{key}/gt").visible
        tab.set(viewer.controls["point_size"], 2.0)
        assert _until(lambda: viewer.replay_state()["point_scale"] == 2.0) and viewer.wait_idle(5)
        other = next(t for t, g in viewer.run_options().items() if g == "live-icp")
        tab.set(viewer.controls["run"], other)  # pick another run: its panel shows, this one hides
        assert _until(lambda: viewer.replay_state()["selected"] == "live-icp") and viewer.wait_idle(5)
        assert not viewer.scene_node(f"/jobs/{key}").visible
        # the tab's camera was framed on the picked run: it looks at the middle of its map
        (client,) = viewer.server.get_clients().values()
        gt_map = np.concatenate([f @ p[:2, :2].T + p[:2, 2] for f, p in zip(seq.frames, seq.poses, strict=True)])
        middle = (gt_map.min(0) + gt_map.max(0)) / 2
        np.testing.assert_allclose(client.camera.look_at[:2], middle, rtol=0.05)
        tab.set(viewer.controls["live"], True)
        assert _until(lambda: viewer.replay_state()["live"]) and viewer.wait_idle(5)
    finally:
        tab.close()
    viewer.set_replay(live=True)
    viewer.set_display(show_gt=True, point_scale=1.0)
    assert viewer.wait_idle(5) and viewer.scene_node(f"/jobs/{key}/gt").visible


def test_history_is_bounded_and_replays() -> None:
    h = History(limit=8)
    for i in range(1, 101):
        h.append(Snapshot(i, float(i), None, {"total": 1.0 / i}, None))
    assert len(h) <= 8 and h.items[0].iteration == 1 and h.latest.iteration == 100
    assert h.at(0).iteration == 1 and h.at(1000).iteration == 100
    its = h.iterations()
    assert its == sorted(its) and h.at(its[3] + 1).iteration == its[3]


def test_close_frees_the_port(seq) -> None:
    v = ViewerServer(port=0)
    port = v.port
    assert v.host == "127.0.0.1"
    v.sink("j", "icp", seq)
    assert v.wait_idle(5)
    v.close()
    v.close()  # idempotent
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))  # the port is free again
    again = ViewerServer(port=port)
    try:
        assert again.port == port
    finally:
        again.close()


def test_viewer_settings_are_one_section_of_the_service_settings(monkeypatch) -> None:
    """The viewer's limits come from the service's ``viewer`` section (env ``STREP_VIEWER__*``);
    the defaults are the viewer's former constructor defaults."""
    defaults = ViewerSettings()
    assert (defaults.max_points_per_job, defaults.max_rate_hz, defaults.history_limit) == (30_000, 10.0, 256)
    assert (defaults.max_pose_markers, defaults.frame_nodes_max, defaults.max_jobs) == (64, 512, 32)
    assert defaults.chart_interval == 0.5
    monkeypatch.setenv("STREP_VIEWER__MAX_JOBS", "3")
    monkeypatch.setenv("STREP_VIEWER__MAX_RATE_HZ", "4")
    settings = Settings().viewer
    assert settings.max_jobs == 3 and settings.max_rate_hz == 4.0 and settings.history_limit == 256
    with pytest.raises(ValueError, match="greater than 0"):
        ViewerSettings(max_rate_hz=0)
    v = ViewerServer(port=0, settings=settings)
    try:
        assert v.settings.max_jobs == 3 and v.interval == 0.25  # pushes at most 4 per second per job
    finally:
        v.close()


def test_3d_poses_are_drawn_in_the_ground_truth_frame(viewer) -> None:
    room = load_input("sample:sim3d-room")
    gt = g.pose_to_vector(room.poses)
    est = g.pose_to_vector(g.inverse(room.poses[0])[None] @ room.poses)  # frame 0 at identity
    sink = viewer.sink("room", "fake3d", room, select=True)
    sink.emit(IterationEvent(iteration=1, total=1, elapsed=0.1, poses=pose_list(est)))
    assert viewer.wait_idle(5)
    key = viewer.jobs()["room"]["key"]
    _assert_shows(viewer, key, pose_list(est))  # each frame carries its own estimated pose
    anchor = viewer.scene_node(f"/jobs/{key}/est")  # ... and the anchor G_0 inv(T_0) = G_0
    np.testing.assert_allclose(anchor.position, room.poses[0][:3, 3], atol=1e-5)
    np.testing.assert_allclose(anchor.wxyz, rotations_to_wxyz(room.poses[0][:3, :3]), atol=1e-5)
    shown = np.asarray(viewer.scene_node(f"/jobs/{key}/trajectory").points)
    np.testing.assert_allclose(shown[:, 0], poses_to_matrices(gt)[:-1, :3, 3], atol=1e-4)


def test_layout_without_ground_truth_follows_the_estimate(viewer, seq, icp_events) -> None:
    import dataclasses

    blind = dataclasses.replace(seq, poses=None)
    viewer.load_job("blind-a", "a", blind, icp_events, group="blind", select=True)
    viewer.load_job("blind-b", "b", blind, icp_events, group="blind")
    assert viewer.wait_idle(5) and viewer.wait_idle(5)
    jobs = viewer.jobs()
    assert f"/jobs/{jobs['blind-a']['key']}/gt" not in viewer.node_names()
    est = poses_to_matrices(icp_events[-1].poses)
    final_map = np.concatenate([f @ p[:2, :2].T + p[:2, 3] for f, p in zip(seq.frames, est, strict=True)])
    width = final_map[:, 0].max() - final_map[:, 0].min()
    pa = np.asarray(viewer.scene_node(f"/jobs/{jobs['blind-a']['key']}").position)
    pb = np.asarray(viewer.scene_node(f"/jobs/{jobs['blind-b']['key']}").position)
    assert width < pb[0] - pa[0] < 1.5 * width


def test_loss_exponent_keeps_small_losses_readable() -> None:
    assert loss_exponent([np.array([3.2e-4, 1e-4])]) == -4  # drawn as 3.2 and 1 (x 1e-4)
    assert loss_exponent([np.array([0.5, 0.02]), np.array([np.nan, 7.0])]) == 0
    assert loss_exponent([np.array([2.5e4])]) == 4
    assert loss_exponent([np.array([0.0])]) == 0 and loss_exponent([]) == 0


def test_chart_draws_chamfer_sized_losses_in_a_power_of_ten(viewer, seq) -> None:
    gt = g.pose_to_vector(seq.poses)
    sink = viewer.sink("tiny-loss", "tiny-loss", seq, select=True)
    sink.emit(
        StartEvent(
            method="fake", sequence=seq.name, frames=len(seq), dims=2, unit="px", total_iterations=3,
            initial_guess="identity",
        )
    )  # fmt: skip
    for i in range(1, 4):
        time.sleep(CHART_INTERVAL if i == 3 else 0.0)  # the chart is redrawn at most every chart_interval
        sink.emit(
            IterationEvent(
                iteration=i, total=3, elapsed=0.1 * i, losses={"total": 4e-4 / i, "chamfer": 3e-4 / i},
                poses=pose_list(gt),
            )
        )  # fmt: skip
    assert viewer.wait_idle(5)
    info = viewer.jobs()["tiny-loss"]
    assert info["chart"][:2] == ["loss/total", "loss/chamfer"] and info["chart_exponent"] == -4


def test_stage_line_follows_the_run() -> None:
    snap = lambda it: Snapshot(it, 1.0, None, {}, 0.5)  # noqa: E731
    kw = {"start_ate": 0.069, "unit": "px", "finished": False}
    assert stage_line("load", None, **kw) == "stage: loading the sequence"
    assert stage_line("init:multiway", None, **kw) == "stage: warm start (multiway)"
    assert stage_line("init:multiway", snap(0), **kw) == "stage: warm start (multiway) done, ATE 0.069 px"
    assert stage_line(None, snap(0), **kw) == "stage: starting, ATE 0.069 px"
    assert stage_line("optimise", snap(5), **kw) == "stage: optimising (from ATE 0.069 px)"
    assert stage_line("init:multiway", snap(5), **kw) == "stage: optimising (from ATE 0.069 px)"
    assert stage_line("write", snap(5), **kw) == "stage: writing files"
    assert stage_line("optimise", snap(5), **{**kw, "finished": True}) is None


def test_side_panel_shows_the_stage_and_hides_terms_that_are_off(viewer, seq) -> None:
    """Before: "stage: init:multiway" at iteration 5, and a flat occupancy curve at 0 for every run."""
    gt = pose_list(g.pose_to_vector(seq.poses))
    sink = viewer.sink("staged", "strep", seq, select=True)
    sink.emit(StageEvent(stage="init:multiway", elapsed=0.1))
    sink.emit(
        StartEvent(
            method="strep", sequence=seq.name, frames=len(seq), dims=2, unit="px", total_iterations=10,
            initial_guess="multiway",
        )
    )  # fmt: skip
    assert viewer.wait_idle(5)
    text = viewer._jobs["staged"].nodes["gui/text"]
    assert "stage: warm start (multiway)" in text.content
    sink.emit(IterationEvent(iteration=0, total=10, elapsed=1.0, losses={}, poses=gt, ate=0.069))
    assert viewer.wait_idle(5)
    assert "stage: warm start (multiway) done, ATE 0.069 px" in text.content
    for i in (5, 10):
        time.sleep(CHART_INTERVAL)
        losses = {"total": 0.02 / i, "chamfer": 0.02 / i, "occupancy": 0.0}
        sink.emit(IterationEvent(iteration=i, total=10, elapsed=1.0 + i, losses=losses, poses=gt, ate=0.06))
        assert viewer.wait_idle(5)
    assert "stage: optimising (from ATE 0.069 px)" in text.content and "init:multiway" not in text.content
    assert "occupancy" not in text.content and "chamfer" in text.content
    assert viewer.jobs()["staged"]["chart"] == ["loss/total", "loss/chamfer", "ate"]  # no occupancy curve
    viewer.remove_job("staged")


def test_another_run_starts_live_with_its_own_iteration(viewer, seq, icp_events) -> None:
    """Before: after a reload the slider kept 40, from another run, while the labels said 150."""
    viewer.load_job("slider-a", "icp", seq, icp_events, select=True)
    assert viewer.wait_idle(5)
    viewer.set_replay(iteration=20)
    assert viewer.wait_idle(5) and viewer.controls["iteration"].value == 20
    short = [e for e in icp_events if e.kind != "iteration" or e.iteration <= 40]
    viewer.load_job("slider-b", "icp-short", seq, short)
    viewer.select("slider-b")
    assert viewer.wait_idle(5)
    state = viewer.replay_state()
    assert state["selected"] == "slider-b" and state["live"] and not state["playing"]
    assert viewer.controls["iteration"].value == viewer.jobs()["slider-b"]["iteration"]
    viewer.set_replay(live=True)


def test_a_map_spread_beyond_the_ground_truth_pushes_its_neighbour_away(viewer, seq) -> None:
    """From scratch a failing run's map is far wider than the ground truth's: its panel grows
    and the next one moves beyond it (the README's no-link panel lay under strep's)."""
    gt = seq.poses.copy()
    spread = gt.copy()
    dx = gt[:, :2, 2] - gt[0, :2, 2]
    factor = 10.0 if dx[:, 0].max() >= -dx[:, 0].min() else -10.0  # steps 10x longer, towards +x
    spread[:, :2, 2] = factor * dx + gt[0, :2, 2]
    for job_id, poses in (("spread", spread), ("right", gt)):
        sink = viewer.sink(job_id, job_id, seq, group="spread-group", select=True)
        sink.emit(IterationEvent(iteration=1, total=1, elapsed=0.1, poses=pose_list(g.pose_to_vector(poses))))
    assert viewer.wait_idle(5) and viewer.wait_idle(5)
    jobs = viewer.jobs()
    a, b = jobs["spread"]["key"], jobs["right"]["key"]

    def world_x(key: str, poses: np.ndarray) -> np.ndarray:
        """x of the map as drawn: panel offset + anchor + frame poses, as the viewer places it."""
        panel = np.asarray(viewer.scene_node(f"/jobs/{key}").position)
        est = poses_to_matrices(pose_list(g.pose_to_vector(poses)))
        anchor = display_anchor(est, poses_to_matrices(pose_list(g.pose_to_vector(gt))))
        shown = anchor[None] @ est
        pts = np.concatenate([f @ p[:2, :2].T + p[:2, 3] for f, p in zip(seq.frames, shown, strict=True)])
        return pts[:, 0] + panel[0]

    xa, xb = world_x(a, spread), world_x(b, gt)
    gt_width = xb.max() - xb.min()
    assert xa.max() - xa.min() > 2.0 * gt_width  # the spread map really is wider
    assert xa.max() < xb.min()  # ... and lies wholly left of its neighbour


def test_an_unknown_event_kind_changes_nothing_shown(viewer, seq, icp_events) -> None:
    """A kind without a reducer is counted, never drawn as an iteration."""

    class Note:
        kind = "note"
        iteration = 5
        ate = 123.0

    sink = viewer.sink("noted", "icp", seq, select=True)
    for ev in icp_events[:2]:
        sink.emit(ev)
    sink.emit(Note())
    assert viewer.wait_idle(5)
    job = viewer.jobs()["noted"]
    assert job["events"] == 3 and job["history"] == 1 and job["iteration"] == icp_events[1].iteration
    assert "123" not in viewer._jobs["noted"].nodes["/jobs/noted/label"].text
    viewer.remove_job("noted")


def test_a_comparisons_panels_follow_its_methods_order(viewer, seq, icp_events) -> None:
    """Before: panels and colours in the order the jobs arrived (the page's reversed, often)."""
    identity = ListSink()
    run(seq, RunConfig(method="identity"), sink=identity)
    title = "sim2d-small: icp vs identity"
    viewer.load_job("ord-id", "identity", seq, identity.events, group="ord", group_title=title, select=True)
    viewer.load_job("ord-icp", "icp", seq, [ev.model_dump() for ev in icp_events], group="ord", group_title=title)
    assert viewer.wait_idle(10)
    keys = {j: viewer.jobs()[j]["key"] for j in ("ord-icp", "ord-id")}
    x = {j: float(np.asarray(viewer.scene_node(f"/jobs/{k}").position)[0]) for j, k in keys.items()}
    assert x["ord-icp"] < x["ord-id"]
    assert [viewer._jobs[j].index for j in ("ord-icp", "ord-id")] == [0, 1]  # the page's colours' order
    folders = [viewer._jobs[j].nodes["gui/folder"].order for j in ("ord-icp", "ord-id")]
    assert folders[0] < folders[1], folders  # the side panel lists them in the same order
    # finished: the status line says so (before: "N run(s); replay: live"), the figures are labelled
    assert viewer.gui.status.content == "finished: Play replays it, the Iteration slider steps through it"
    text = viewer._jobs["ord-icp"].nodes["gui/text"].content
    m = icp_events[-1].metrics
    assert f"finished: ATE {m['ate']:.3g} px, point L2 {m['point_l2']:.3g} px, time {m['wall_seconds']:.3g} s" in text
    assert "wall_seconds" not in text and "point_l2" not in text
    viewer.remove_job("ord-id")
    viewer.remove_job("ord-icp")


def test_the_total_loss_is_not_hidden_under_an_equal_term(viewer, seq) -> None:
    """The total is drawn first and wider, so a term equal to it (the only one on) leaves its
    edges showing (before: both 2 px, the chamfer curve drawn over the total's)."""
    gt = pose_list(g.pose_to_vector(seq.poses))
    sink = viewer.sink("equal-terms", "strep", seq, select=True)
    for i in (1, 2):
        time.sleep(CHART_INTERVAL)
        sink.emit(
            IterationEvent(
                iteration=i, total=2, elapsed=0.1 * i, losses={"total": 0.1 / i, "chamfer": 0.1 / i}, poses=gt
            )
        )
    assert viewer.wait_idle(5)
    job = viewer._jobs["equal-terms"]
    assert job.chart_series[:2] == ("loss/total", "loss/chamfer")
    total, chamfer = job.chart.series[1], job.chart.series[2]
    assert total["width"] >= 2 * chamfer["width"], (total, chamfer)
    viewer.remove_job("equal-terms")


def test_the_viewers_modules_import_each_other_one_way() -> None:
    """No circle in app/viewer, counting imports made for annotations (before: controls named
    ViewerServer, which imports the pusher, which imports the controls)."""
    import ast
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "app" / "viewer"
    graph: dict[str, set[str]] = {}
    for path in folder.glob("*.py"):
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("app.viewer"):
                names = [node.module.removeprefix("app.viewer").lstrip(".")] if node.module != "app.viewer" else []
                names += [a.name for a in node.names if node.module == "app.viewer"]
                deps |= {n for n in names if (folder / f"{n}.py").exists()}
        graph[path.stem] = deps - {path.stem}

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        return any(d == goal or (d not in seen and reaches(d, goal, seen | {d})) for d in graph.get(start, ()))

    circles = sorted(m for m in graph if m != "__init__" and reaches(m, m, {m}))
    assert not circles, {m: sorted(graph[m]) for m in circles}
