"""Registration settings: `RegistrationParams` in the sequence's unit, derived from the data.

Data-derived lengths (`resolve_params`), with ``s = Sequence.scale()`` (median point range):

* correspondence distance ``d = icp.correspondence_fraction * s``; ICP runs coarse to fine over
  ``icp.scales * d``;
* voxel ``v = icp.voxel_fraction * s``;
* 3D normal radius ``normals.radius_factor * max(v, h)``, ``h`` the median spacing of
  neighbouring points (`point_spacing`), so that sparse clouds still find neighbours;
  2D normals from the ``normals.neighbours`` nearest neighbours in the plane.

The figures behind the defaults: docs/design/scan-matching.md and the classical methods'
docstring (`strep_core.methods.classical`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from strep_core.config import ClassicalConfig
from strep_core.correlative import CorrelativeParams
from strep_core.scanmatch import ScanMatchParams
from strep_core.sequence import Sequence


@dataclass(frozen=True)
class RegistrationParams:
    """Absolute registration settings for one sequence; build them with `resolve_params`.

    Attributes:
        dim: spatial dimension D of the frames (2 or 3).
        max_correspondence: finest ICP correspondence distance (sequence unit).
        scales: coarse-to-fine multipliers of ``max_correspondence``, one ICP stage each.
        iterations: ICP iterations per stage.
        min_fitness: ICP stages matching fewer source points than this fraction are discarded.
        kernel: Tukey kernel width as a fraction of each stage's distance; ``None``: plain L2.
        voxel: voxel size for downsampling (sequence unit); ``None``: keep every point.
        normal_neighbours: 2D normals: neighbours of the in-plane PCA (the point included).
        normal_radius: 3D normals: search radius (sequence unit).
        normal_max_nn: 3D normals: at most this many neighbours within the radius.
        local_map: incremental ICP registers frame k to the union of this many previous frames.
        threads: CPU threads Open3D may use (1 makes runs bit-for-bit repeatable).
        yaw_search: extra yaw offsets (radians) tried as starting guesses of the coarsest ICP
            stage (`strep_core.registration.pairwise`); empty: the initial guess alone.
        yaw_axis: unit axis of those turns in the source sensor's frame (``z`` in 2D).
        search_voxel: 3D: the yaw search's starts run on copies of the clouds downsampled to
            this voxel (sequence unit), the later stages on the clouds as prepared; ``None``:
            every stage on the prepared clouds.
        yaw_refine: 3D: before the yaw search, the axis moves to the mean of the source's
            normals within this angle (radians) of it (its floor and ceiling: a hand-held
            LiDAR tilts; `strep_core.registration.lidar.refine_axis`); 0: off.
        yaw_verify: 3D: when the best start's trimmed distance exceeds this many voxels of the
            clouds the search ran on, every other heading is tried too (at the search's step);
            0: off.
        degeneracy: keep the guess's translation along weakly constrained directions (see
            `strep_core.registration.pairwise`); 0: off.
        correlative: 2D: also start from a correlative scan match (`strep_core.registration.pairwise`).
        velocity_prior: incremental ICP starts each pair from the previous pair's estimated
            motion (constant velocity) instead of the initial guess's relative motion.
        global_match: 2D: also start from a global scan match (see `icp_pair`).
        prior_stop: a global match's step prior shorter than this (sequence unit) is a stop:
            the median of the last longer steps replaces it (`step_prior`); 0: never.
    """

    dim: int
    max_correspondence: float
    scales: tuple[float, ...] = (1.0,)
    iterations: int = 50
    min_fitness: float = 0.0
    kernel: float | None = None
    voxel: float | None = None
    normal_neighbours: int = 6
    normal_radius: float = 1.0
    normal_max_nn: int = 30
    local_map: int = 1
    threads: int = 1
    yaw_search: tuple[float, ...] = ()
    yaw_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    search_voxel: float | None = None
    yaw_refine: float = 0.0
    yaw_verify: float = 0.0
    degeneracy: float = 0.0
    correlative: CorrelativeParams | None = None
    velocity_prior: bool = False
    global_match: ScanMatchParams | None = None
    prior_stop: float = 0.0

    @property
    def planar(self) -> bool:
        return self.dim == 2


def resolve_params(seq: Sequence, cfg: ClassicalConfig) -> RegistrationParams:
    """Turn a `ClassicalConfig` into absolute lengths for ``seq`` (rules in the module doc)."""
    s = seq.scale()
    icp, normals, scan = cfg.icp, cfg.normals, cfg.scanmatch
    voxel = icp.voxel if icp.voxel is not None else icp.voxel_fraction * s
    normal_radius = normals.radius if normals.radius is not None else 1.0
    if normals.radius is None and seq.dim == 3:  # 2D normals use neighbour counts, not a radius
        normal_radius = normals.radius_factor * max(voxel, point_spacing(seq))
    axis: tuple[float, float, float] | None = None
    if icp.yaw_axis is not None:
        a = np.asarray(icp.yaw_axis, dtype=np.float64)
        x, y, z = (float(c) for c in a / np.linalg.norm(a))
        axis = (x, y, z)
    d = icp.max_correspondence if icp.max_correspondence is not None else icp.correspondence_fraction * s
    correlative = None
    if cfg.correlative.window > 0 and seq.dim == 2:
        correlative = CorrelativeParams(
            window=cfg.correlative.window * d,
            yaw_window=float(np.radians(cfg.correlative.yaw_window)),
            yaw_step=float(np.radians(1.0)),
            resolution=d / 7.0,
            sigma=d / 3.5,
        )
    global_match = None
    if seq.dim == 2 and scan.consecutive != "off":
        global_match = ScanMatchParams(
            window=scan.window * s,
            resolution=scan.resolution * s,
            yaw_step=float(np.radians(scan.yaw_step)),
            yaw_window=float(np.radians(scan.yaw_window)),
            max_range=scan.range * s,
            prior_weight=scan.prior,
            prior_scale=s,
        )
    return RegistrationParams(
        dim=seq.dim,
        max_correspondence=d,
        scales=tuple(icp.scales),
        iterations=icp.iterations,
        min_fitness=icp.min_fitness,
        kernel=icp.kernel,
        voxel=voxel if voxel > 0 else None,
        normal_neighbours=normals.neighbours,
        normal_radius=normal_radius,
        normal_max_nn=normals.max_nn,
        local_map=icp.local_map_frames,
        threads=cfg.threads,
        yaw_search=yaw_offsets(icp.yaw_search, icp.yaw_step) if seq.dim == 2 or axis is not None else (),
        yaw_axis=(0.0, 0.0, 1.0) if axis is None or seq.dim == 2 else axis,
        search_voxel=icp.search_voxel * voxel if seq.dim == 3 and icp.search_voxel > 1 and voxel > 0 else None,
        yaw_refine=float(np.radians(icp.yaw_refine)) if seq.dim == 3 else 0.0,
        yaw_verify=icp.yaw_verify if seq.dim == 3 else 0.0,
        degeneracy=icp.degeneracy,
        correlative=correlative,
        velocity_prior=icp.motion_prior == "velocity",
        global_match=global_match,
        prior_stop=scan.prior_stop * s,
    )


def yaw_offsets(half_width_deg: float, step_deg: float) -> tuple[float, ...]:
    """Nonzero yaw offsets ``+-step, +-2 step, ...`` up to ``half_width`` (degrees in, radians out),
    nearest first."""
    if half_width_deg <= 0 or step_deg <= 0:
        return ()
    n = int(np.floor(half_width_deg / step_deg + 1e-9))
    return tuple(float(np.radians(sign * i * step_deg)) for i in range(1, n + 1) for sign in (1, -1))


def point_spacing(seq: Sequence, *, max_frames: int = 4) -> float:
    """Median distance from a point to its nearest neighbour in the same frame (sequence unit).

    Measured on up to ``max_frames`` evenly spaced frames; the density of the data, where
    `Sequence.scale` is its extent (sparse 2D scan lines: about 0.02 of the scale; dense
    depth images subsampled 4x: about 0.007).
    """
    from scipy.spatial import cKDTree

    step = max(1, len(seq) // max(1, max_frames))
    d = np.concatenate([cKDTree(f).query(f, k=2)[0][:, 1] for f in seq.frames[::step][:max_frames]])
    d = d[d > 0]
    return float(np.median(d)) if len(d) else seq.scale() * 1e-3
