"""Rigid registration with Open3D, shared by the classical methods and the learned methods' warm
starts, split along its seams:

* `params`: `RegistrationParams`, the settings in the sequence's unit, derived from the data;
* `clouds`: Open3D clouds with normals, planar projections;
* `pairwise`: point-to-plane ICP of a pair, coarse to fine, with its guards (`icp_pair`);
* `chain`: the incremental chain along a sequence (`incremental_icp`);
* `loops`: loop closures, proposed by proximity or by the global scan matcher, verified;
* `posegraph`: the pose graph of a chain and its loops, optimised.

Conventions (see `strep_core.geometry`): poses are homogeneous ``(D+1, D+1)`` matrices,
local -> world; lengths are in the sequence's unit (pixels or metres); a pairwise result maps
source coordinates into target coordinates. Optional guards (yaw search, weak directions,
correlative and global starts) are off by default; the profile a run picks from its data turns
them on (`strep_core.profiles`).
"""

from strep_core.registration.chain import (
    IncrementalResult,
    incremental_icp,
    pair_report,
    prepare_frames,
    step_prior,
)
from strep_core.registration.clouds import (
    from_se3,
    information_matrix,
    make_cloud,
    normals_2d,
    open3d_quiet,
    prepare_frame,
    project_planar,
    transform_cloud,
)
from strep_core.registration.loops import LoopClosure, global_loop_closures, loop_candidates, proximity_loop_closures
from strep_core.registration.pairwise import PairResult, align_frames, icp_pair, keep_guess_where_weak
from strep_core.registration.params import RegistrationParams, point_spacing, resolve_params, yaw_offsets
from strep_core.registration.posegraph import optimise_pose_graph

__all__ = [
    "IncrementalResult",
    "LoopClosure",
    "PairResult",
    "RegistrationParams",
    "align_frames",
    "from_se3",
    "global_loop_closures",
    "icp_pair",
    "incremental_icp",
    "information_matrix",
    "keep_guess_where_weak",
    "loop_candidates",
    "make_cloud",
    "normals_2d",
    "open3d_quiet",
    "optimise_pose_graph",
    "pair_report",
    "point_spacing",
    "prepare_frame",
    "prepare_frames",
    "project_planar",
    "proximity_loop_closures",
    "resolve_params",
    "step_prior",
    "transform_cloud",
    "yaw_offsets",
]
