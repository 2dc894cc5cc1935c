"""Registration metrics: ATE, point-wise L2 to the ground-truth map, RPE.

All lengths are in the sequence's unit (pixels or metres), angles in degrees where named so.
Estimated trajectories are compared after a rigid alignment (rotation + translation, no
scale; Umeyama 1991) of estimated positions onto ground-truth positions, because an
unsupervised registration fixes the map only up to a rigid motion.
"""

from __future__ import annotations

from collections.abc import Sequence as Seq

import numpy as np

from strep_core import geometry as g


def align_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``(D, D)`` and translation ``(D,)`` minimising ``sum |R src_i + t - dst_i|^2``.

    Args:
        src: ``(N, D)`` points to move.
        dst: ``(N, D)`` target points.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(src.shape[1])
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[-1, -1] = -1.0
    rot = u @ s @ vt
    return rot, mu_d - rot @ mu_s


def alignment_pose(est_poses: np.ndarray, gt_poses: np.ndarray) -> np.ndarray:
    """The rigid transform ``(D+1, D+1)`` that best maps estimated positions onto ground truth."""
    return g.homogeneous(*align_rigid(g.translation(est_poses), g.translation(gt_poses)))


def aligned(est_poses: np.ndarray, gt_poses: np.ndarray) -> np.ndarray:
    """Estimated poses ``(K, D+1, D+1)`` moved by `alignment_pose` into the ground truth's frame."""
    return alignment_pose(est_poses, gt_poses)[None] @ est_poses


def ate(est_poses: np.ndarray, gt_poses: np.ndarray) -> float:
    """Absolute trajectory error: RMSE of positions after rigid alignment.

    Args:
        est_poses, gt_poses: ``(K, D+1, D+1)`` local -> world poses.
    """
    diff = g.translation(aligned(est_poses, gt_poses)) - g.translation(gt_poses)
    return float(np.sqrt((diff**2).sum(-1).mean()))


def _strided(points: np.ndarray, max_points: int | None) -> np.ndarray:
    if max_points and len(points) > max_points:
        return points[:: int(np.ceil(len(points) / max_points))]
    return points


def point_l2(
    frames: Seq[np.ndarray],
    est_poses: np.ndarray,
    gt_poses: np.ndarray,
    *,
    max_points_per_frame: int | None = 2000,
) -> float:
    """Point-wise L2 between the registered map and the ground-truth map.

    Every point is placed once by the estimate and once by ground truth; the estimated map is
    rigidly aligned onto the true one *using those point pairs* (Umeyama), then the mean
    distance between each point's two placements is returned. Aligning on the points rather
    than on camera positions keeps the figure meaningful when the trajectory barely moves
    (a camera turning on the spot, views around an object), where a position-only alignment
    leaves the rotation undetermined.

    Args:
        frames: ``K`` local point arrays ``(N_i, D)``.
        est_poses, gt_poses: ``(K, D+1, D+1)``.
        max_points_per_frame: evenly strided subsample per frame to bound the cost
            (``None``: all points).
    """
    pts = [_strided(f, max_points_per_frame) for f in frames]
    p_est = np.concatenate([g.apply(t, p) for t, p in zip(est_poses, pts, strict=True)])
    p_gt = np.concatenate([g.apply(t, p) for t, p in zip(gt_poses, pts, strict=True)])
    rot, t = align_rigid(p_est, p_gt)
    return float(np.linalg.norm(p_est @ rot.T + t - p_gt, axis=1).mean())


def pairwise_errors(est_poses: np.ndarray, gt_poses: np.ndarray, *, max_frames: int = 200) -> dict[str, float]:
    """Errors of the relative pose between every pair of frames ``i < j``.

    ``(G_i^-1 G_j)^-1 (E_i^-1 E_j)``: its angle (degrees) and translation (sequence unit);
    invariant to any rigid motion of either trajectory, so it needs no alignment at all.
    Sequences longer than ``max_frames`` use an evenly strided subset of frames.
    """
    idx = np.arange(len(est_poses))[:: int(np.ceil(len(est_poses) / max_frames))]
    i, j = np.triu_indices(len(idx), 1)
    i, j = idx[i], idx[j]
    err = g.relative(g.relative(gt_poses[i], gt_poses[j]), g.relative(est_poses[i], est_poses[j]))
    rot = np.degrees(g.rotation_angle(err))
    trans = np.linalg.norm(g.translation(err), axis=-1)
    return {
        "pair_rot_err_mean_deg": float(rot.mean()),
        "pair_rot_err_max_deg": float(rot.max()),
        "pair_trans_err_mean": float(trans.mean()),
        "pair_trans_err_max": float(trans.max()),
    }


def rpe(est_poses: np.ndarray, gt_poses: np.ndarray, *, delta: int = 1) -> dict[str, float]:
    """Relative pose error over ``delta`` frames: translation RMSE and mean rotation error (deg)."""
    rel_e = g.relative(est_poses[:-delta], est_poses[delta:])
    rel_g = g.relative(gt_poses[:-delta], gt_poses[delta:])
    err = g.relative(rel_g, rel_e)
    trans = np.linalg.norm(g.translation(err), axis=-1)
    rot = np.degrees(g.rotation_angle(err))
    return {"rpe_trans": float(np.sqrt((trans**2).mean())), "rpe_rot_deg": float(rot.mean())}


def evaluate(frames: Seq[np.ndarray], est_poses: np.ndarray, gt_poses: np.ndarray) -> dict[str, float]:
    """All metrics of an estimate against ground truth, as a flat dict."""
    out = {"ate": ate(est_poses, gt_poses), "point_l2": point_l2(frames, est_poses, gt_poses)}
    out.update(rpe(est_poses, gt_poses))
    out.update(pairwise_errors(est_poses, gt_poses))
    return out
