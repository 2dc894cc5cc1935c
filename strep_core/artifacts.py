"""The trained model as a file: ``model.pt``, written beside a learned run's results and read
back by ``--from-model`` (test-time mode with ``--freeze``).

An artefact is a plain dict of tensors and values (``torch.load(..., weights_only=True)``
reads it), versioned by `ARTIFACT_VERSION`; the loop in `strep_core.optimize` builds it and
starts from it, and nothing here knows that loop.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from strep_core.config import ModelConfig
from strep_core.errors import ConfigError
from strep_core.model import StrepModel

ARTIFACT_VERSION = 1


def save_model(artifact: dict[str, Any], path: str | Path) -> None:
    """Write a model artefact (``MethodOutput.artifacts["model"]``) with `torch.save`."""
    torch.save(artifact, Path(path))


def load_model(path: str | Path) -> dict[str, Any]:
    """Read a model artefact written by `save_model` (tensors and plain values only)."""
    try:
        art = torch.load(Path(path), map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as exc:
        raise ConfigError(f"cannot read model {path}: {exc}") from exc
    if not isinstance(art, dict) or art.get("version") != ARTIFACT_VERSION:
        raise ConfigError(f"{path} is not a STREP model artefact (version {ARTIFACT_VERSION})")
    return art


def model_artifact(model: StrepModel, model_cfg: ModelConfig, *, dim: int, scale: float) -> dict[str, Any]:
    """The artefact of a trained model: its networks, ``w`` and latents, and how it was built."""

    def cpu(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu().clone() for k, v in sd.items()}

    lat = model.latents
    return {
        "version": ARTIFACT_VERSION,
        "variant": model.variant,
        "dim": dim,
        "scale": scale,
        "model_config": model_cfg.model_dump(),
        "decoder": cpu(model.decoder.state_dict()),
        "occupancy": cpu(model.occupancy.state_dict()),
        "w": None if lat is None or lat.w is None else lat.w.detach().cpu().clone(),
        "latents": None if lat is None else lat.raw.detach().cpu().clone(),
    }


def load_into(model: StrepModel, art: dict[str, Any]) -> None:
    """Copy an artefact's networks and link weight ``w`` into ``model`` (its latents stay fresh)."""
    model.decoder.load_state_dict(art["decoder"])
    model.occupancy.load_state_dict(art["occupancy"])
    if model.latents is not None and model.latents.w is not None:
        if art["w"] is None:
            raise ConfigError("the saved model has no link weight w; it cannot start a linked strep run")
        with torch.no_grad():
            model.latents.w.copy_(art["w"])
