"""Settings chosen from the data: named profiles and the probe that picks one.

Every overlay of the project lives here, in one form: a plain dict of config values per
section. A run's fields left out take the overlay's values, fields given keep theirs
(`strep_core.resolve.resolve`, the one place they are applied). Two kinds, stacked by `overlay`:

* the start's overlay (`START_OVERLAYS`): the learned methods' settings from scratch;
* the data's profile (`PROFILES`, and its part for runs from scratch, `SCRATCH_OVERLAYS`).

`RunConfig.profile` names a profile, or ``"auto"`` (the default): then `probe` measures a few
frame pairs of the sequence and picks one. The resolved config records the choice and its
reason (``profile``, ``profile_reason``), so ``config.json`` says what was chosen and why, and,
since a saved config holds every field, re-runs the same settings whatever the probe would say.

Profiles (values in `PROFILES`; measurements in ``docs/design/profiles.md``):

* ``laser-keyframes``: planar scans taken far apart (CARMEN keyframes: steps of 0.2 to 0.6 of the
  scale, turns up to 80 degrees): the global scan matcher on every consecutive pair
  (`strep_core.scanmatch`), and it also proposes and verifies the pose graph's loop closures;
  each pair starts from the previous pair's motion, and along a corridor (a direction the matched
  normals barely constrain) the translation stays at that guess (``icp.degeneracy``); the learned
  methods' corrections along such directions are penalised (``loss.weak_weight``).
* ``laser-dense``: planar scans a small step apart (DeepMapping's v1_pose0, the simulated 2D
  lidar): plain coarse-to-fine ICP; the global matcher costs 4x and changes nothing there.
* ``depth-turning``: a depth camera that turns in place by tens of degrees between frames (the
  simulated AVD-like walks): ICP searches yaw about the camera's vertical axis in 30-degree
  steps, finer stages, weak directions keep the guess, frame to frame.
* ``depth-handheld``: a depth camera moved smoothly (7-Scenes): the defaults.
* ``lidar``: a 3D LiDAR (lidar_balm): voxel and normals from the median range, a yaw search about
  the vertical estimated from the scans on coarser copies, Tukey kernel, constant velocity;
  ``kiss`` with KISS-ICP's own voxel rule, the (99.9th-percentile) range / 100 (docs/design/lidar.md).
* ``none``: the defaults, no probe.

The probe (`probe`) reads what the reader recorded of the sensor (``Sequence.meta["sensor"]``:
``kind`` ``"laser"`` or ``"depth"``, a laser's field of view, a camera's vertical axis in its own
frame) and, on up to `PROBE_PAIRS` consecutive pairs spread over the sequence:

* 2D: the heading change and step length of the global scan match of the pair (every heading,
  +-1.5 scales), and the overlap at identity (share of points within 0.05 scale of the other scan);
* 3D: the heading change that best overlaps the pair, turning about the camera's vertical axis
  (every 5 degrees up to 60), and the overlap at identity.

A 3D sequence in metres from no image grid is a ``lidar`` when its rays cover at least
`LIDAR_AZIMUTH` degrees of azimuth and reach `LIDAR_RANGE` at the 95th percentile, or one of these
with LiDAR per-point fields (`_lidar_evidence`, `strep_core.registration.lidar.sensor_geometry`).
Other rules: 2D is ``laser-keyframes`` when the median step exceeds `KEYFRAME_STEP` scales or the
largest turn exceeds `KEYFRAME_TURN` degrees, else ``laser-dense``; 3D is ``depth-turning`` when a
vertical axis is known and the largest turn reaches `TURNING_TURN` degrees, else
``depth-handheld``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core.sequence import Sequence
from strep_core.voxels import first_per_cell

# Overlays per config section. Values are what the benchmark measured best (docs/design/profiles.md).
PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "laser-keyframes": {
        "classical": {
            "scanmatch": {"consecutive": "on", "yaw_window": 120.0},
            "posegraph": {"loop_global": "on"},
            "icp": {"motion_prior": "velocity", "degeneracy": 0.05},
        },
        # hold corrections along corridor axes: belgioioso[300:400] 0.337 -> 0.131 m (docs/design/warm-start.md)
        "loss": {"weak_weight": 0.1},
    },
    "laser-dense": {"classical": {"scanmatch": {"consecutive": "off"}, "posegraph": {"loop_global": "off"}}},
    "depth-turning": {
        "classical": {
            "icp": {
                "yaw_search": 30.0,
                "yaw_step": 30.0,
                "yaw_axis": (0.0, -1.0, 0.0),  # replaced by the sensor's own vertical axis when known
                "scales": [1.0, 0.5, 0.25],
                "degeneracy": 0.05,
                "kernel": 1.0,  # Tukey at each stage's distance: pose graph 0.352 -> 0.199 m (profiles.md)
                "local_map_frames": 1,
            }
        }
    },
    "depth-handheld": {"classical": {}},
    # a LiDAR: voxel 0.04 of the median range, normals within 5 voxels, a yaw search of +-45 degrees about the
    # vertical axis estimated from the scans (`overlay`) on 2x coarser copies, Tukey kernel, constant
    # velocity: lidar_balm icp 4.98 -> 0.005 m (docs/design/lidar.md)
    "lidar": {
        "classical": {
            "icp": {
                "voxel_fraction": 0.04,
                "yaw_search": 45.0,
                "yaw_step": 15.0,
                "yaw_axis": (0.0, 0.0, 1.0),  # replaced by the axis estimated from the scans
                "yaw_refine": 25.0,
                "search_voxel": 2.0,
                # a right match leaves 0.28 search voxels, wrong ones 0.40 and more: below, the full circle
                "yaw_verify": 0.35,
                "kernel": 1.0,
                "local_map_frames": 1,
                "motion_prior": "velocity",
            },
            "normals": {"radius_factor": 5.0},
            # loops from an odometry good to centimetres: the finest stage, 3 a frame (multiway 2.3 -> 1.7 s a scan)
            "posegraph": {"loop_max_candidates": 3, "loop_scales": [0.5]},
        }
    },
    "none": {},
}
PROFILE_NAMES = tuple(PROFILES)

# The learned methods' settings per start, under the profile's. "pose-graph" (refine a classical
# warm start) is the sections' defaults; "scratch" (from identity, no classical step) is measured
# in docs/design/from-scratch.md.
START_OVERLAYS: dict[str, dict[str, dict[str, Any]]] = {
    "pose-graph": {},
    "scratch": {
        "model": {"link_init": 1.0},
        # temporal pairs (Huber) form the chain; from halfway, loop pairs (truncated, weighted by
        # window / span) close it: v1_pose0 1.75 -> 0.47 px (docs/design/from-scratch.md)
        "loss": {
            "robust": "huber",
            "loop_radius_fraction": 0.5,
            "loop_after": 0.5,
            "loop_robust": "truncated",
            "loop_weight": "span",
        },
        "optim": {"lr_latent": 1e-2, "iterations": 1000},
    },
}

# Further overlays for runs from scratch (`RunConfig.start` "scratch"), over `START_OVERLAYS["scratch"]`.
# A camera turning 30 degrees in place shares about half its view with the next frame: the Huber
# Chamfer's minimum then lies at half the turn, the trimmed one's at the turn, and frames two apart
# barely overlap; the camera stays level, so corrections turn about its vertical axis only
# (docs/design/from-scratch.md, "Simulated 3D walks").
SCRATCH_OVERLAYS: dict[str, dict[str, dict[str, Any]]] = {
    "depth-turning": {
        "model": {"planar_axis": [0.0, -1.0, 0.0]},  # replaced by the sensor's own vertical axis when known
        "loss": {"robust": "trimmed", "window": 1},
    },
}

PROBE_PAIRS = 12  # consecutive pairs measured, spread evenly over the sequence
KEYFRAME_STEP = 0.15  # median step (fraction of the scale) above which 2D scans are keyframes
KEYFRAME_TURN = 15.0  # largest turn (degrees) above which 2D scans are keyframes
TURNING_TURN = 15.0  # largest turn (degrees) from which a depth camera is turning in place
OVERLAP_RADIUS = 0.05  # overlap: share of points within this fraction of the scale


@dataclass
class ProbeResult:
    """The probe's choice, why, and what it measured (degrees, fractions of the scale)."""

    profile: str
    reason: str
    measures: dict[str, Any] = field(default_factory=dict)


def sensor_of(seq: Sequence) -> dict[str, Any]:
    """What the reader recorded of the sensor (``meta["sensor"]``), else what the dimension says:
    a planar laser in 2D, an unknown 3D sensor."""
    sensor = seq.meta.get("sensor") if isinstance(seq.meta, dict) else None
    if isinstance(sensor, dict):
        return sensor
    return {"kind": "laser", "planar": True} if seq.dim == 2 else {"kind": "unknown"}


def _pairs(k: int, n: int = PROBE_PAIRS) -> list[int]:
    """Indices j of up to ``n`` pairs (j-1, j) spread evenly over ``k`` frames."""
    if k < 2:
        return []
    return sorted({int(j) for j in np.linspace(1, k - 1, min(n, k - 1)).round()})


def _overlap(source: np.ndarray, target_tree: Any, radius: float) -> float:
    d, _ = target_tree.query(source, k=1, distance_upper_bound=radius)
    return float(np.mean(np.isfinite(d)))


def _subsample(points: np.ndarray, cell: float, limit: int = 3000) -> np.ndarray:
    out = points[first_per_cell(points, cell)]
    if len(out) > limit:
        out = out[np.linspace(0, len(out) - 1, limit).astype(np.int64)]
    return out


def _measure_2d(seq: Sequence, s: float) -> dict[str, Any]:
    from scipy.spatial import cKDTree

    from strep_core.scanmatch import ScanMatcher, ScanMatchParams

    params = ScanMatchParams(window=1.5 * s, resolution=0.025 * s, max_range=8.0 * s)
    turns, steps, overlaps = [], [], []
    assert seq.origins is not None
    for j in _pairs(len(seq)):
        src, tgt = seq.frames[j] - seq.origins[j], seq.frames[j - 1] - seq.origins[j - 1]
        overlaps.append(_overlap(src, cKDTree(tgt), OVERLAP_RADIUS * s))
        found = ScanMatcher(tgt, params).match(src, np.eye(3))
        turns.append(abs(float(np.degrees(np.arctan2(found.pose[1, 0], found.pose[0, 0])))))
        steps.append(float(np.linalg.norm(found.pose[:2, 2])) / s)
    return {"pairs": len(turns), "turn_deg": turns, "step": steps, "overlap": overlaps}


def _measure_3d(seq: Sequence, s: float, axis: np.ndarray | None) -> dict[str, Any]:
    from scipy.spatial import cKDTree

    from strep_core import geometry as g

    turns, overlaps = [], []
    yaws = np.radians(np.arange(-60, 61, 5))
    assert seq.origins is not None
    for j in _pairs(len(seq)):
        src = _subsample(seq.frames[j] - seq.origins[j], 0.02 * s)
        tree = cKDTree(_subsample(seq.frames[j - 1] - seq.origins[j - 1], 0.02 * s))
        overlaps.append(_overlap(src, tree, OVERLAP_RADIUS * s))
        if axis is None:
            continue
        scores = [_overlap(src @ g.so3_exp(axis * y).T, tree, OVERLAP_RADIUS * s) for y in yaws]
        turns.append(abs(float(np.degrees(yaws[int(np.argmax(scores))]))))
    return {"pairs": len(overlaps), "turn_deg": turns, "overlap": overlaps}


LIDAR_AZIMUTH = 90.0  # degrees of azimuth a LiDAR's scans cover at least (a depth camera: about 60)
LIDAR_RANGE = 8.0  # metres: a LiDAR's 95th-percentile range reaches this (7-Scenes: 3 m)
LIDAR_FIELDS = {"intensity", "reflectivity", "ring", "time", "timestamp", "t", "line", "tag"}


def _lidar_evidence(seq: Sequence, sensor: dict[str, Any]) -> tuple[str, dict[str, Any]] | None:
    """``(reason, measures)`` when a 3D sequence in metres, from no image grid, looks like a LiDAR:
    a wide field of view and ranges of tens of metres, or one of these and a LiDAR's per-point
    fields (`LIDAR_FIELDS`, or a Velodyne ``.bin``); else ``None``."""
    from strep_core.registration.lidar import sensor_geometry

    if seq.dim != 3 or seq.unit != "m" or sensor.get("kind") in ("depth", "laser"):
        return None
    geo = sensor_geometry(seq)
    fields = sorted(LIDAR_FIELDS & {str(f).lower() for f in seq.meta.get("point_fields", []) or []})
    if seq.meta.get("format") == "velodyne-bin":
        fields.append("velodyne .bin")
    wide, far = geo["azimuth_deg"] >= LIDAR_AZIMUTH, geo["range_p95"] >= LIDAR_RANGE
    said = f"azimuth {geo['azimuth_deg']:.0f} deg, 95th-percentile range {geo['range_p95']:.1f} m"
    if not ((wide and far) or (fields and (wide or far))):
        return None
    extra = f"; fields {', '.join(fields)}" if fields else ""
    return f"LiDAR: {said} (>= {LIDAR_AZIMUTH:.0f} deg, >= {LIDAR_RANGE:.0f} m){extra}", {
        "lidar": {**geo, "fields": fields}
    }


def probe(seq: Sequence) -> ProbeResult:
    """Measure a few consecutive pairs of ``seq`` and pick a profile (rules in the module doc)."""
    from strep_core.registration import point_spacing

    s = seq.scale()
    sensor = sensor_of(seq)
    measures: dict[str, Any] = {"sensor": sensor, "scale": s, "spacing": point_spacing(seq) / s}
    if len(seq) < 2:
        return ProbeResult("none", "a single frame: nothing to measure", measures)
    if seq.dim == 2:
        measures.update(_measure_2d(seq, s))
        step, turn = float(np.median(measures["step"])), float(np.max(measures["turn_deg"]))
        said = f"{measures['pairs']} pairs: median step {step:.2f} scale, largest turn {turn:.0f} deg"
        if step > KEYFRAME_STEP or turn > KEYFRAME_TURN:
            limits = f"above {KEYFRAME_STEP} scale or {KEYFRAME_TURN:.0f} deg"
            return ProbeResult("laser-keyframes", f"planar laser, {said} ({limits})", measures)
        limits = f"within {KEYFRAME_STEP} scale and {KEYFRAME_TURN:.0f} deg"
        return ProbeResult("laser-dense", f"planar laser, {said} ({limits})", measures)
    lidar = _lidar_evidence(seq, sensor)
    if lidar is not None:
        measures.update(lidar[1])
        return ProbeResult("lidar", lidar[0], measures)
    axis = sensor.get("vertical_axis")
    unit_axis = None
    if axis is not None:
        a = np.asarray(axis, dtype=np.float64)
        unit_axis = a / np.linalg.norm(a)
    measures.update(_measure_3d(seq, s, unit_axis))
    overlap = float(np.median(measures["overlap"]))
    if unit_axis is None:
        return ProbeResult(
            "depth-handheld",
            f"3D, no vertical axis known: no yaw search; {measures['pairs']} pairs, median overlap {overlap:.2f}",
            measures,
        )
    turn = float(np.max(measures["turn_deg"]))
    said = f"{measures['pairs']} pairs: largest turn {turn:.0f} deg, median overlap {overlap:.2f}"
    kind = sensor.get("kind", "3D")
    if turn >= TURNING_TURN:
        return ProbeResult("depth-turning", f"{kind} sensor, {said} (>= {TURNING_TURN:.0f} deg)", measures)
    return ProbeResult("depth-handheld", f"{kind} sensor, {said} (< {TURNING_TURN:.0f} deg)", measures)


def overlay(name: str, seq: Sequence | None = None, *, start: str = "pose-graph") -> dict[str, dict[str, Any]]:
    """The overlay of a run per section: the start's (`START_OVERLAYS`), profile ``name``'s over
    it, and from scratch the profile's `SCRATCH_OVERLAYS` part over both; ``depth-turning``
    turns about the sensor's own vertical axis when ``seq`` records one."""
    from strep_core.config import merge

    out: dict[str, dict[str, Any]] = copy.deepcopy(START_OVERLAYS.get(start, {}))
    parts = [PROFILES[name], SCRATCH_OVERLAYS.get(name, {}) if start == "scratch" else {}]
    for part in parts:
        for section, values in copy.deepcopy(part).items():
            out[section] = merge(out.get(section, {}), values)
    if name == "lidar" and seq is not None:
        from strep_core.registration.lidar import kiss_voxel, vertical_axis

        known = sensor_of(seq).get("vertical_axis")
        axis = vertical_axis(seq) if known is None else known
        out["classical"]["icp"]["yaw_axis"] = tuple(float(c) for c in axis)
        out["classical"]["kiss"] = {"voxel": kiss_voxel(seq)}  # KISS-ICP's own rule
    if name == "depth-turning" and seq is not None:
        axis = sensor_of(seq).get("vertical_axis")
        if axis is not None:
            out["classical"]["icp"]["yaw_axis"] = tuple(float(c) for c in axis)
            if "planar_axis" in out.get("model", {}):
                out["model"]["planar_axis"] = [float(c) for c in axis]
    return out


def choose(seq: Sequence, name: str, reason: str | None = None) -> tuple[str, str]:
    """The profile of a run and why: the probe's choice when ``name`` is ``"auto"``, else ``name``."""
    if name != "auto":
        return name, reason or "given"
    try:
        found = probe(seq)
    except Exception as exc:  # a probe that cannot measure (a few points a frame) is no error: defaults
        return "none", f"probe failed ({type(exc).__name__}: {exc}): the defaults"
    return found.profile, f"probe: {found.reason}"
