"""The one resolve stage: a run's request and its scene to the settings that run.

`resolve` is called once, by the runner (`strep_core.runner.run_scene`), before the initial
guess; the command line, the service's worker, ``strep bench`` and ``strep reproduce`` all come
through there, so the same request on the same frames gives the same resolved config. In order:

1. the start: ``auto`` is ``scratch`` when ``init`` is ``identity``, else ``pose-graph``;
2. the profile: the probe's choice (`strep_core.profiles.choose`) or the one named;
3. the overlays (`strep_core.profiles.overlay`: the start's, then the profile's) under the
   fields the request set (``model_fields_set``, nested): what was given always wins;
4. every ``auto`` and every length left to the data: the initial guess, the device, torch's
   threads, the learned methods' batch, and the classical lengths and radii (``s =
   Sequence.scale()``, rules of `strep_core.registration.params`).

The resolved config holds concrete values, so resolving it again changes nothing and its
``config.json`` re-runs it. Requests travel between processes as
``model_dump_json(exclude_unset=True)``: a full dump would mark every default as given, and no
profile or overlay would apply (docs/design/resolve.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from strep_core.config import RunConfig, merge
from strep_core.sequence import Sequence

# The learned methods' warm start under ``start="pose-graph"``: the pose graph refines
# incremental ICP with loop closures, the networks then refine it (docs/design/warm-start.md).
LEARNED_WARM_START = "multiway"


@dataclass(frozen=True)
class ResolvedRun:
    """What runs: ``config`` holds every value (no ``auto``, no length left to the data);
    ``requested`` is the config as given."""

    config: RunConfig
    requested: RunConfig
    learned: bool


def resolve_device(name: str) -> str:
    """``cpu`` without loading torch; else `strep_core.device.resolve_device` (``auto``: ``cuda``
    when torch sees a GPU, else ``cpu``; ``cuda`` without one is a `ConfigError`)."""
    if name == "cpu":
        return "cpu"
    from strep_core.device import resolve_device as on_torch

    return on_torch(name)


def resolve_start(start: str, init: str) -> str:
    """``auto``: ``scratch`` from identity, else ``pose-graph``."""
    if start != "auto":
        return start
    return "scratch" if init == "identity" else "pose-graph"


def _init(config: RunConfig, scene: Sequence, *, learned: bool) -> str:
    if config.init != "auto":
        return config.init
    if learned and config.start == "pose-graph":
        return LEARNED_WARM_START
    if config.start == "scratch":
        return "identity"
    return "odometry" if scene.initial_poses is not None else "identity"


def _classical(config: RunConfig, scene: Sequence) -> dict[str, Any]:
    """The classical lengths and switches left to the data, as config values (sequence unit)."""
    from strep_core.registration import point_spacing

    cfg = config.classical
    s = scene.scale()
    icp, normals, scan, pg, kiss = cfg.icp, cfg.normals, cfg.scanmatch, cfg.posegraph, cfg.kiss
    out: dict[str, dict[str, Any]] = {"icp": {}, "normals": {}, "scanmatch": {}, "posegraph": {}, "kiss": {}}
    planar = scene.dim == 2
    if icp.max_correspondence is None:
        out["icp"]["max_correspondence"] = icp.correspondence_fraction * s
    voxel = icp.voxel if icp.voxel is not None else icp.voxel_fraction * s
    if icp.voxel is None and voxel > 0:
        out["icp"]["voxel"] = voxel
    spacing = point_spacing(scene) if (kiss.voxel is None or (normals.radius is None and not planar)) else 0.0
    if normals.radius is None and not planar:  # 2D normals count neighbours, no radius
        out["normals"]["radius"] = normals.radius_factor * max(voxel, spacing)
    if kiss.voxel is None:
        out["kiss"]["voxel"] = kiss.voxel_spacing * spacing
    consecutive = scan.consecutive if scan.consecutive != "auto" else ("on" if planar else "off")
    out["scanmatch"]["consecutive"] = consecutive
    if pg.loop_radius is None:
        out["posegraph"]["loop_radius"] = pg.loop_radius_fraction * s
    loop_global = pg.loop_global
    if loop_global == "auto":
        loop_global = "on" if planar and consecutive == "on" else "off"
    out["posegraph"]["loop_global"] = loop_global
    if pg.odometry_uncertain == "auto":
        robust = planar and consecutive == "on" and loop_global == "on"  # multiway's own rule
        out["posegraph"]["odometry_uncertain"] = "on" if robust else "off"
    if pg.frontend == "auto":  # planar lasers: submaps, loops, GTSAM (docs/design/laser-slam.md)
        from strep_core.registration.laser_slam import is_planar_laser

        out["posegraph"]["frontend"] = "submaps" if is_planar_laser(scene) else "icp"
    return out


def resolve(config: RunConfig, scene: Sequence) -> ResolvedRun:
    """``config`` (as requested) resolved on ``scene`` (its frames selected): see the module doc.

    Raises `MethodError` for an unknown method and `ConfigError` for a device that is missing.
    """
    from strep_core import profiles
    from strep_core.methods import get

    learned = get(config.method).learned
    given = config.model_dump(exclude_unset=True)
    start = resolve_start(config.start, config.init)
    name, reason = profiles.choose(scene, config.profile, config.profile_reason)
    values = merge(profiles.overlay(name, scene, start=start), given)
    values.update(start=start, profile=name, profile_reason=reason)
    cfg = RunConfig.build(**values)
    autos: dict[str, Any] = {
        "init": _init(cfg, scene, learned=learned),
        "device": resolve_device(cfg.device),
        "threads": cfg.threads or os.cpu_count() or 1,
        "classical": _classical(cfg, scene),
    }
    if learned and cfg.optim.batch_frames == "auto":
        from strep_core.batching import batch_size

        autos["optim"] = {"batch_frames": batch_size(len(scene), "auto")}
    return ResolvedRun(config=RunConfig.build(**merge(values, autos)), requested=config, learned=learned)
