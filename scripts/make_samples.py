"""Regenerate the bundled samples in ``sample_sequences/`` and their ``manifest.json``.

Usage: ``python scripts/make_samples.py [--out FOLDER]`` (default: `strep_core.samples.samples_dir`).

Deterministic: the simulators are seeded and the ``.npz`` archives are rewritten with fixed
timestamps, so running it twice gives byte-identical files. Fails if a file exceeds 2 MB.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from strep_core.io.npz import write_npz
from strep_core.samples import MANIFEST, MAX_BYTES, Manifest, SampleInfo, samples_dir
from strep_core.sequence import Sequence
from strep_core.sim import simulate_2d, simulate_3d

GENERATORS: dict[str, Callable[..., Sequence]] = {
    "strep_core.sim.simulate_2d": simulate_2d,
    "strep_core.sim.simulate_3d": simulate_3d,
}

SPECS: list[dict[str, Any]] = [
    {
        "name": "sim2d-small",
        "generator": "strep_core.sim.simulate_2d",
        "params": {"seed": 1, "frames": 64, "rays": 256, "noise": 0.0, "map_seed": 1},
        "description": "Simulated 2D lidar, DeepMapping style: 64 scans x 256 rays over 360 degrees "
        "on a 1024 x 1024 px floor plan; steps turn -10..10 degrees and move 0..16 px. Quick demo.",
    },
    {
        "name": "sim2d",
        "generator": "strep_core.sim.simulate_2d",
        "params": {"seed": 2, "frames": 256, "rays": 256, "noise": 0.0, "map_seed": 2},
        "description": "Simulated 2D lidar, DeepMapping style: 256 scans x 256 rays on a 1024 x 1024 px "
        "floor plan with rooms, doors, a corridor and boxes, as in DeepMapping's v1_pose0.",
    },
    {
        "name": "sim3d-room",
        "generator": "strep_core.sim.simulate_3d",
        "params": {"seed": 0, "frames": 16, "stride": 12, "noise": 0.0},
        "description": "Simulated depth camera in a furnished room, Active Vision Dataset style: 16 frames "
        "on a 300 mm grid with headings 30 degrees apart, 640 x 480 depth subsampled every 12 px.",
    },
]


def _normalise_zip(path: Path) -> None:
    """Rewrite a zip archive with fixed timestamps so identical content gives identical bytes."""
    tmp = path.with_name(path.name + ".tmp")
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(tmp, "w") as zout:
        for item in zin.infolist():
            info = zipfile.ZipInfo(item.filename, date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zout.writestr(info, zin.read(item), compresslevel=9)
    tmp.replace(path)


def build(out: Path) -> list[SampleInfo]:
    """Write every sample of `SPECS` and the manifest into ``out``; return the entries."""
    out.mkdir(parents=True, exist_ok=True)
    infos = []
    for spec in SPECS:
        params = dict(spec["params"])
        seq = GENERATORS[spec["generator"]](**params)
        seq.name = spec["name"]
        file = f"{spec['name']}.npz"
        write_npz(seq, out / file)
        _normalise_zip(out / file)
        data = (out / file).read_bytes()
        infos.append(
            SampleInfo(
                name=spec["name"],
                file=file,
                dims=seq.dim,  # type: ignore[arg-type]
                frames=len(seq),
                points=seq.num_points,
                unit=seq.unit,
                seed=params["seed"],
                generator=spec["generator"],
                params=params,
                description=spec["description"],
                bytes=len(data),
                sha256=hashlib.sha256(data).hexdigest(),
            )
        )
    manifest = Manifest(samples=infos)
    (out / MANIFEST).write_text(json.dumps(manifest.model_dump(), indent=2) + "\n", encoding="utf-8")
    return infos


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="folder to write (default: the samples folder)")
    args = parser.parse_args(argv)
    out = samples_dir() if args.out is None else args.out
    infos = build(out)
    too_big = [i for i in infos if i.bytes > MAX_BYTES]
    for i in infos:
        print(f"{i.file:20s} {i.dims}D {i.frames:4d} frames {i.points:7d} points {i.bytes / 1024:7.1f} KiB")
    if too_big:
        print(f"error: over {MAX_BYTES} bytes: {', '.join(i.file for i in too_big)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
