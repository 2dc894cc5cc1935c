"""Framing the viewer's camera on the shown run: every tab's camera and the initial one.

Pusher thread only. The camera looks at the panels from above, slightly tilted, with clip
planes scaled to the scene (viser's default far plane, 1000, hides maps in pixels).
"""

from __future__ import annotations

import math

import numpy as np
import viser

from app.viewer.panel import Job
from app.viewer.scene import union_bbox


def camera_pose(box: tuple[np.ndarray, np.ndarray], *, fov: float, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera ``(position, look_at)`` that shows ``box`` (world, z up) from above, slightly
    tilted, filling most of a view of vertical field of view ``fov`` (radians) and ``aspect``
    (width / height); it looks at the middle of the box."""
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    center, extent = (lo + hi) / 2.0, hi - lo
    tan_v = math.tan(fov / 2.0)
    distance = max(
        float(extent[0]) / (2.0 * tan_v * aspect * 0.8),  # width across the view, a margin each side
        float(max(extent[1], extent[2])) / (2.0 * tan_v * 0.8),  # depth and height up the view
        1e-6,
    )
    direction = np.array([0.0, -0.3, 1.0]) / math.hypot(0.3, 1.0)
    return center + distance * direction, center


def frame_camera(server: viser.ViserServer, members: list[Job], *, clients: set[int] | None = None) -> None:
    """Point every tab's camera (or only ``clients``) and the initial camera at ``members``'
    panels: their ground truth and their estimates as shown now (not as laid out)."""
    if not members:
        return
    box = None
    for job in members:
        shown = job.shown_box or job.box_of()
        for lo, hi in (b for b in (job.scene.gt_bbox(), shown) if b is not None):
            box = union_bbox(box, (lo + job.offset, hi + job.offset))
    assert box is not None
    size = float(max(np.max(box[1] - box[0]), 1e-6))
    near, far = max(1e-3, 1e-4 * size), max(1000.0, 20.0 * size)
    camera = server.initial_camera
    position, look_at = camera_pose(box, fov=camera.fov, aspect=4 / 3)
    camera.near, camera.far = near, far
    # position first: viser's camera position setter drags look_at along with it
    camera.position = tuple(position)
    camera.look_at = tuple(look_at)
    for client_id, client in server.get_clients().items():
        if clients is not None and client_id not in clients:
            continue
        cam = client.camera
        try:
            width, height, fov = cam.image_width, cam.image_height, cam.fov
        except AssertionError:  # the client has not reported its camera yet
            width, height, fov = 0, 0, camera.fov
        aspect = width / height if width > 0 and height > 0 else 4 / 3
        position, look_at = camera_pose(box, fov=fov, aspect=aspect)
        cam.near, cam.far = near, far
        cam.position = position
        cam.look_at = look_at
