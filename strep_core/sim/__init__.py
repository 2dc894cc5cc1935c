"""Seeded simulators of sequences with ground truth: 2D lidar on a floor plan, 3D depth in a room.

`lidar2d` needs numpy and scipy only; `depth3d` imports Open3D inside its functions, so
importing this package stays light.
"""

from strep_core.sim.depth3d import (
    Camera,
    Room,
    camera_pose,
    free_grid,
    make_room,
    make_trajectory_3d,
    raycasting_scene,
    render_depth,
    sequence_room,
    simulate_3d,
)
from strep_core.sim.floorplan import free_distance, make_map
from strep_core.sim.lidar2d import (
    cast_rays,
    make_trajectory,
    scan,
    scan_sequence,
    sequence_map,
    simulate_2d,
    write_deepmapping,
)

__all__ = [
    "Camera",
    "Room",
    "camera_pose",
    "cast_rays",
    "free_distance",
    "free_grid",
    "make_map",
    "make_room",
    "make_trajectory",
    "make_trajectory_3d",
    "raycasting_scene",
    "render_depth",
    "scan",
    "scan_sequence",
    "sequence_map",
    "sequence_room",
    "simulate_2d",
    "simulate_3d",
    "write_deepmapping",
]
