"""Config files of format version 1, read under the current names.

`RENAMED` (frozen: version 1's keys) maps every old key (dotted, from the run config's root) to
its new path. A run config of version 1 (a ``config.json`` without ``config_version``, or a
request that gives none: ``--set classical.icp_scales=...``, a REST job body) is rewritten by
`migrate` before validation, with one logged warning naming the new keys; an old key given beside
its new one wins. Keys in neither table are left for validation to refuse. A later rename bumps
`strep_core.config.CONFIG_VERSION` and adds its own step here, instead of growing this table.
"""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger("strep_core.config")

_CLASSICAL = {
    "max_correspondence": "icp.max_correspondence",
    "correspondence_fraction": "icp.correspondence_fraction",
    "icp_scales": "icp.scales",
    "icp_iterations": "icp.iterations",
    "icp_min_fitness": "icp.min_fitness",
    "icp_kernel": "icp.kernel",
    "icp_yaw_search": "icp.yaw_search",
    "icp_motion_prior": "icp.motion_prior",
    "icp_yaw_step": "icp.yaw_step",
    "icp_yaw_axis": "icp.yaw_axis",
    "icp_degeneracy": "icp.degeneracy",
    "local_map_frames": "icp.local_map_frames",
    "voxel": "icp.voxel",
    "voxel_fraction": "icp.voxel_fraction",
    "icp_correlative": "correlative.window",
    "icp_correlative_yaw": "correlative.yaw_window",
    "icp_global": "scanmatch.consecutive",
    "icp_global_window": "scanmatch.window",
    "icp_global_resolution": "scanmatch.resolution",
    "icp_global_yaw_step": "scanmatch.yaw_step",
    "icp_global_yaw_window": "scanmatch.yaw_window",
    "icp_global_range": "scanmatch.range",
    "icp_global_prior": "scanmatch.prior",
    "icp_global_prior_stop": "scanmatch.prior_stop",
    "normal_neighbours": "normals.neighbours",
    "normal_radius": "normals.radius",
    "normal_radius_factor": "normals.radius_factor",
    "normal_max_nn": "normals.max_nn",
    **{
        name: f"posegraph.{name}"
        for name in (
            "loop_radius",
            "loop_radius_fraction",
            "loop_min_gap",
            "loop_min_fitness",
            "loop_max_candidates",
            "loop_scales",
            "edge_prune_threshold",
            "loop_preference",
            "loop_global",
            "loop_global_radius",
            "loop_global_score",
            "odometry_uncertain",
            "loop_global_every",
            "loop_global_candidates",
            "loop_global_turn",
        )
    },
    "kiss_voxel": "kiss.voxel",
    "kiss_voxel_spacing": "kiss.voxel_spacing",
    "kiss_reference_scale": "kiss.reference_scale",
    "kiss_max_points_per_voxel": "kiss.max_points_per_voxel",
    "kiss_initial_threshold": "kiss.initial_threshold",
    "kiss_min_motion": "kiss.min_motion",
    "kiss_prior": "kiss.prior",
    "event_interval": "event_interval_frames",
}

# old key -> new key, both dotted from the run config's root
RENAMED: dict[str, str] = {
    **{f"classical.{old}": f"classical.{new}" for old, new in _CLASSICAL.items()},
    "loss.loop_radius": "loss.loop_radius_fraction",
}

_BY_SECTION: dict[str, dict[str, list[str]]] = {}
for _old, _new in RENAMED.items():
    _section, _key = _old.split(".", 1)
    _BY_SECTION.setdefault(_section, {})[_key] = _new.split(".")[1:]


def _rewrite(section: str, data: dict[str, Any], renamed: list[str]) -> dict[str, Any]:
    table = _BY_SECTION.get(section, {})
    if not any(key in table for key in data):
        return data
    out = {k: v for k, v in data.items() if k not in table}
    for key, value in data.items():
        if key not in table:
            continue
        *parents, leaf = table[key]
        node = out
        for p in parents:
            child = node.get(p)
            if hasattr(child, "model_dump"):  # a section model given beside: its set fields, under the old key
                child = child.model_dump(exclude_unset=True)
            child = dict(child) if isinstance(child, dict) else {}
            node[p] = child
            node = child
        node[leaf] = value
        renamed.append(f"{section}.{key} -> {section}.{'.'.join(table[key])}")
    return out


def _warn(renamed: list[str]) -> None:
    if renamed:
        log.warning("config keys renamed, the old names are read for now: %s", ", ".join(renamed))


def migrate(data: Any) -> Any:
    """A whole run config (a dict) with the old keys of every section moved to their new paths."""
    if not isinstance(data, dict):
        return data
    renamed: list[str] = []
    out = dict(data)
    for section in _BY_SECTION:
        if isinstance(out.get(section), dict):
            out[section] = _rewrite(section, out[section], renamed)
    _warn(renamed)
    return out
