"""Bundled sample sequences: small simulated ``.npz`` files with ground truth, ready to run.

The samples live in ``sample_sequences/`` at the repository root (beside this package, which
is installed editable), described by ``sample_sequences/manifest.json``; set the environment
variable ``STREP_SAMPLES_DIR`` to use another folder (read at every call). Sources written
``sample:NAME`` (on the CLI, in job requests) name a sample; `resolve` turns them into paths.

The files are made by ``scripts/make_samples.py`` from the seeded simulators in
`strep_core.sim`; the manifest records each generator and its parameters, so every sample
can be rebuilt exactly.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from strep_core.errors import FormatError
from strep_core.sequence import FrameSelection, Sequence

SAMPLES_ENV = "STREP_SAMPLES_DIR"
PREFIX = "sample:"
MANIFEST = "manifest.json"
MAX_BYTES = 2 * 1024 * 1024  # every bundled file stays under this size


class SampleInfo(BaseModel):
    """One entry of ``manifest.json``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(description="short name, used as `sample:NAME`")
    file: str = Field(description="file name inside the samples folder")
    dims: Literal[2, 3] = Field(description="spatial dimension D")
    frames: int = Field(ge=2, description="number of frames K")
    points: int = Field(ge=0, description="total number of points over all frames")
    unit: Literal["px", "m"] = Field(description="unit of every length")
    seed: int = Field(description="seed passed to the generator")
    generator: str = Field(description="dotted name of the function that made it")
    params: dict[str, Any] = Field(description="keyword arguments of the generator (seed included)")
    description: str = Field(description="one or two sentences for listings")
    bytes: int = Field(ge=0, description="file size in bytes")
    sha256: str = Field(description="hex SHA-256 of the file")


class Manifest(BaseModel):
    """``manifest.json``: a version and the list of samples."""

    model_config = ConfigDict(extra="forbid")

    version: int = 1
    samples: list[SampleInfo]


def samples_dir() -> Path:
    """The samples folder: ``$STREP_SAMPLES_DIR`` or ``<repository>/sample_sequences``."""
    env = os.environ.get(SAMPLES_ENV)
    return Path(env) if env else Path(__file__).resolve().parents[1] / "sample_sequences"


def read_manifest(folder: Path | None = None) -> Manifest:
    """Parse ``manifest.json`` of ``folder`` (default `samples_dir`).

    Raises:
        FormatError: the manifest is missing, not JSON, or does not match `Manifest`.
    """
    path = (samples_dir() if folder is None else folder) / MANIFEST
    try:
        return Manifest.model_validate(json.loads(path.read_text(encoding="utf-8")))
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no sample manifest (set {SAMPLES_ENV}?)") from exc
    except (OSError, json.JSONDecodeError, ValidationError) as exc:
        raise FormatError(f"{path}: not a valid sample manifest ({exc})") from exc


def list_samples() -> list[SampleInfo]:
    """Every bundled sample, in manifest order."""
    return list(read_manifest().samples)


def sample_info(name: str) -> SampleInfo:
    """The manifest entry of sample ``name``.

    Raises:
        FormatError: no sample has this name (the message lists the known ones).
    """
    samples = list_samples()
    for info in samples:
        if info.name == name:
            return info
    known = ", ".join(s.name for s in samples) or "none"
    raise FormatError(f"unknown sample {name!r}; known samples: {known}")


def sample_path(name: str) -> Path:
    """Path of sample ``name``'s file.

    Raises:
        FormatError: unknown sample, or its file is missing.
    """
    path = samples_dir() / sample_info(name).file
    if not path.is_file():
        raise FormatError(f"sample {name!r}: file {path} is missing")
    return path


def load_sample(name: str, *, frames: str | FrameSelection | None = None) -> Sequence:
    """Read sample ``name`` (optionally a ``start:stop[:step]`` selection of its frames).

    The sequence is named after the sample; ``meta`` holds the sample name, generator and
    parameters.
    """
    from strep_core.io.npz import read_npz

    info = sample_info(name)
    seq = read_npz(sample_path(name), frames=frames)
    seq.name = info.name
    seq.meta.update({"sample": info.name, "generator": info.generator, "params": dict(info.params)})
    return seq


def is_sample(source: str | Path) -> bool:
    """Whether ``source`` names a bundled sample (``sample:NAME``)."""
    return isinstance(source, str) and source.startswith(PREFIX)


def resolve(source: str | Path) -> Path:
    """The path behind a source: ``sample:NAME`` gives the sample's file; anything else is a path.

    Raises:
        FormatError: ``sample:NAME`` with an unknown name or a missing file.
    """
    if is_sample(source):
        return sample_path(str(source)[len(PREFIX) :])
    return Path(source)
