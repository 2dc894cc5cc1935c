"""The bundled samples: manifest, files, loading, `sample:NAME` resolution."""

from __future__ import annotations

import hashlib
import importlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from strep_core import samples
from strep_core.errors import FormatError
from strep_core.samples import (
    MAX_BYTES,
    SAMPLES_ENV,
    is_sample,
    list_samples,
    load_sample,
    resolve,
    sample_path,
    samples_dir,
)

EXPECTED = {"sim2d-small": (2, 64, "px"), "sim2d": (2, 256, "px"), "sim3d-room": (3, 16, "m")}


def test_default_folder_is_beside_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(SAMPLES_ENV, raising=False)
    assert samples_dir() == Path(samples.__file__).resolve().parents[1] / "sample_sequences"
    assert (samples_dir() / "manifest.json").is_file()


def test_manifest_lists_every_file() -> None:
    infos = list_samples()
    names = [i.name for i in infos]
    assert len(set(names)) == len(names)
    assert set(names) == set(EXPECTED)
    on_disk = {p.name for p in samples_dir().iterdir() if p.name != "manifest.json"}
    assert on_disk == {i.file for i in infos}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sample_loads_as_declared(name: str) -> None:
    info = samples.sample_info(name)
    dims, frames, unit = EXPECTED[name]
    assert (info.dims, info.frames, info.unit) == (dims, frames, unit)
    path = sample_path(name)
    data = path.read_bytes()
    assert len(data) == info.bytes < MAX_BYTES
    assert hashlib.sha256(data).hexdigest() == info.sha256
    seq = load_sample(name)
    assert (seq.dim, len(seq), seq.unit, seq.num_points) == (dims, frames, unit, info.points)
    assert seq.name == name and seq.meta["sample"] == name
    assert seq.poses is not None and seq.poses.shape == (frames, dims + 1, dims + 1)
    part = load_sample(name, frames="0:10")
    assert len(part) == 10 and np.array_equal(part.frames[3], seq.frames[3])


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sample_is_rebuilt_by_its_generator(name: str) -> None:
    info = samples.sample_info(name)
    module, attr = info.generator.rsplit(".", 1)
    fresh = getattr(importlib.import_module(module), attr)(**info.params)
    seq = load_sample(name)
    assert info.seed == info.params["seed"]
    assert seq.poses is not None and fresh.poses is not None
    # sin, cos and matrix products differ in the last place across CPUs and BLAS builds: the
    # poses agree to far below a unit of the sample (px or m), not bit for bit
    np.testing.assert_allclose(seq.poses, fresh.poses, rtol=0, atol=1e-9)
    for a, b in zip(seq.frames, fresh.frames, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-4)  # stored as float32


def test_resolve_and_is_sample() -> None:
    assert is_sample("sample:sim2d") and not is_sample("sim2d.npz") and not is_sample(Path("sample:x"))
    assert resolve("sample:sim2d") == sample_path("sim2d")
    assert resolve("data/run.npz") == Path("data/run.npz")
    with pytest.raises(FormatError, match=r"unknown sample 'nope'.*sim2d-small"):
        resolve("sample:nope")
    with pytest.raises(FormatError):
        load_sample("nope")


def test_env_var_moves_the_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = sample_path("sim2d-small")
    shutil.copy(src, tmp_path / src.name)
    manifest = json.loads((src.parent / "manifest.json").read_text())
    manifest["samples"] = [s for s in manifest["samples"] if s["name"] == "sim2d-small"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    monkeypatch.setenv(SAMPLES_ENV, str(tmp_path))
    assert [i.name for i in list_samples()] == ["sim2d-small"]
    assert resolve("sample:sim2d-small") == tmp_path / src.name
    with pytest.raises(FormatError, match="known samples: sim2d-small"):
        sample_path("sim2d")
    (tmp_path / src.name).unlink()
    with pytest.raises(FormatError, match="missing"):
        sample_path("sim2d-small")
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(FormatError, match="not a valid sample manifest"):
        list_samples()
    monkeypatch.setenv(SAMPLES_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(FormatError, match="no sample manifest"):
        list_samples()
