"""Reading a recording back with Rerun's own reader (`rerun.chunk.RrdReader`): what the tests
and the service check a written ``.rrd`` against."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.rrd.blueprint import ITERATION


@dataclass
class RunRecording:
    """One run as read back from a recording.

    Attributes:
        key: the run's entity key (``world/<key>``).
        label: its label (from the label point), when present.
        iterations: distinct ``iteration`` values at which poses were logged, ascending.
        last_poses: ``(K, 4, 4)`` float64: each frame's transform at the last logged
            iteration (the estimated local -> world poses, float32 precision).
        scalars: ``loss/<term>`` and ``ate`` -> ``(iterations, values)``.
        map_iterations: iterations at which a fused map was logged.
        offset: ``(3,)`` the panel's offset in ``world`` (static, the latest layout).
    """

    key: str
    label: str | None
    iterations: list[int]
    last_poses: np.ndarray
    scalars: dict[str, tuple[np.ndarray, np.ndarray]]
    map_iterations: list[int]
    offset: np.ndarray


@dataclass
class RecordingSummary:
    """What a ``.rrd`` written by a recorder holds."""

    application_id: str
    recording_id: str
    entity_paths: list[str]
    runs: dict[str, RunRecording]
    has_blueprint: bool
    views: list[str] = field(default_factory=list)


def read_recording(path: str | Path) -> RecordingSummary:
    """Read a recording back with Rerun's own reader (`rerun.chunk.RrdReader`)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    stores = reader.recordings()
    if not stores:
        raise ValueError(f"{path} holds no recording")
    store = stores[0]
    paths: set[str] = set()
    # (key, k) -> (iteration, row id, translation, mat3x3)
    last: dict[tuple[str, int], tuple[int, bytes, list[float], list[float]]] = {}
    iterations: dict[str, set[int]] = {}
    map_its: dict[str, set[int]] = {}
    labels: dict[str, str] = {}
    offsets: dict[str, tuple[bytes, list[float]]] = {}
    scalars: dict[tuple[str, str], list[tuple[int, bytes, float]]] = {}
    for chunk in reader.stream(store=store):
        entity = chunk.entity_path.lstrip("/")
        paths.add(entity)
        parts = entity.split("/")
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if chunk.is_static:  # the latest static write wins, as in the viewer
            rows = [bytes(r) for r in batch.column("rerun.controls.RowId").to_pylist()]
            if len(parts) == 3 and parts[0] == "world" and parts[2] == "label" and "Points3D:labels" in names:
                for row in batch.column("Points3D:labels").to_pylist():
                    if row:
                        labels[parts[1]] = row[0]
            if len(parts) == 2 and parts[0] == "world" and "Transform3D:translation" in names:
                for rid, t in zip(rows, batch.column("Transform3D:translation").to_pylist(), strict=True):
                    if t and (parts[1] not in offsets or rid > offsets[parts[1]][0]):
                        offsets[parts[1]] = (rid, t[0])
            continue
        if ITERATION not in names:
            continue
        its = batch.column(ITERATION).to_pylist()
        rows = [bytes(r) for r in batch.column("rerun.controls.RowId").to_pylist()]
        if len(parts) == 4 and parts[0] == "world" and parts[2] == "frames" and parts[3].startswith("frame_"):
            key, k = parts[1], int(parts[3].removeprefix("frame_"))
            trans = batch.column("Transform3D:translation").to_pylist()
            mats = batch.column("Transform3D:mat3x3").to_pylist()
            for it, rid, t, m in zip(its, rows, trans, mats, strict=True):
                if it is None or not t or not m:
                    continue
                iterations.setdefault(key, set()).add(it)
                cur = last.get((key, k))
                if cur is None or (it, rid) > (cur[0], cur[1]):
                    last[(key, k)] = (it, rid, t[0], m[0])
        elif len(parts) == 3 and parts[0] == "world" and parts[2] == "map" and "Points3D:positions" in names:
            map_its.setdefault(parts[1], set()).update(i for i in its if i is not None)
        elif len(parts) >= 3 and parts[0] == "metrics" and "Scalars:scalars" in names:
            name = "/".join(parts[2:])
            values = batch.column("Scalars:scalars").to_pylist()
            for it, rid, v in zip(its, rows, values, strict=True):
                if it is not None and v:
                    scalars.setdefault((parts[1], name), []).append((it, rid, float(v[0])))

    runs: dict[str, RunRecording] = {}
    for key in sorted(iterations):
        ks = sorted(k for (kk, k) in last if kk == key)
        poses = np.zeros((len(ks), 4, 4))
        for i, k in enumerate(ks):
            _, _, t, m = last[(key, k)]
            poses[i, :3, :3] = np.asarray(m, dtype=np.float64).reshape(3, 3, order="F")
            poses[i, :3, 3] = t
            poses[i, 3, 3] = 1.0
        curves = {}
        for (kk, name), pts in scalars.items():
            if kk == key:
                pts.sort()
                curves[name] = (np.array([p[0] for p in pts], np.float64), np.array([p[2] for p in pts], np.float64))
        runs[key] = RunRecording(
            key=key,
            label=labels.get(key),
            iterations=sorted(iterations[key]),
            last_poses=poses,
            scalars=curves,
            map_iterations=sorted(map_its.get(key, set())),
            offset=np.asarray(offsets[key][1] if key in offsets else np.zeros(3), dtype=np.float64),
        )
    views: list[str] = []
    for bp in reader.blueprints()[-1:]:  # the latest blueprint sent
        for chunk in reader.stream(store=bp):
            batch = chunk.to_record_batch()
            if "ViewBlueprint:display_name" in batch.schema.names:
                views += [v[0] for v in batch.column("ViewBlueprint:display_name").to_pylist() if v]
    return RecordingSummary(
        application_id=store.application_id,
        recording_id=store.recording_id,
        entity_paths=sorted(paths),
        runs=runs,
        has_blueprint=bool(reader.blueprints()),
        views=sorted(set(views)),
    )
