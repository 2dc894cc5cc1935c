"""The pose graph of ``multiway``: nodes at the incremental chain's poses, odometry edges between
consecutive frames, loop-closure edges (`strep_core.registration.loops`), optimised by Open3D's
Levenberg-Marquardt with a line process that prunes wrong loops. Information matrices come from
`get_information_matrix_from_point_clouds`; 2D runs in 3D at ``z = 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.errors import RegistrationError
from strep_core.registration.clouds import information_matrix
from strep_core.registration.loops import LoopClosure


def optimise_pose_graph(
    clouds: list[Any],
    poses: np.ndarray,
    loops: list[LoopClosure],
    *,
    distance: float,
    odometry_uncertain: bool,
    edge_prune_threshold: float,
    loop_preference: float,
) -> tuple[np.ndarray, int]:
    """Optimise the pose graph of a chain and its loops; node 0 (the reference) stays put.

    Args:
        clouds: the chain's prepared clouds (`IncrementalResult.clouds`).
        poses: ``(K, D+1, D+1)`` the chain's poses (the nodes' start).
        loops: loop-closure edges (uncertain: the line process may prune them).
        distance: correspondence distance of the information matrices and the pruning.
        odometry_uncertain: the odometry edges may be pruned too (drifting keyframe chains).
        edge_prune_threshold, loop_preference: Open3D's `GlobalOptimizationOption`.

    Returns:
        ``(K, 4, 4)`` optimised poses and the number of edges.
    """
    from strep_core._open3d import o3d

    pgo = o3d.pipelines.registration
    poses3 = g.to_se3(np.asarray(poses, dtype=np.float64))
    graph = pgo.PoseGraph()
    for pose in poses3:
        graph.nodes.append(pgo.PoseGraphNode(pose))
    for k in range(1, len(poses3)):
        rel = g.relative(poses3[k - 1], poses3[k])
        info = information_matrix(clouds[k], clouds[k - 1], rel, distance)
        graph.edges.append(pgo.PoseGraphEdge(k, k - 1, rel, info, uncertain=odometry_uncertain))
    for loop in loops:
        info = information_matrix(clouds[loop.j], clouds[loop.i], loop.transformation, distance)
        graph.edges.append(pgo.PoseGraphEdge(loop.j, loop.i, loop.transformation, info, uncertain=True))
    pgo.global_optimization(
        graph,
        pgo.GlobalOptimizationLevenbergMarquardt(),
        pgo.GlobalOptimizationConvergenceCriteria(),
        pgo.GlobalOptimizationOption(
            max_correspondence_distance=distance,
            edge_prune_threshold=edge_prune_threshold,
            preference_loop_closure=loop_preference,
            reference_node=0,
        ),
    )
    optimised = np.stack([np.asarray(node.pose) for node in graph.nodes])
    if not np.isfinite(optimised).all():
        raise RegistrationError("the pose graph optimisation returned non-finite poses")
    return optimised, len(graph.edges)
