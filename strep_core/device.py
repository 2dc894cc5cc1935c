"""The torch device of a run, and section timers that tell the truth on it.

`resolve_device` turns the config's ``device`` (``auto`` by default) into the device a run uses:
the runner's resolve stage records its answer in ``config.json``. `SectionClock` charges wall time
to named sections of the learned loop; on a GPU it synchronises at each lap only when asked
(``profile=True``), so an ordinary run keeps the device busy without host syncs and its sections
are then only a coarse split (docs/design/optimiser.md).
"""

from __future__ import annotations

import time

import torch

from strep_core.errors import ConfigError


def resolve_device(name: str) -> str:
    """``"cuda"`` or ``"cpu"`` for a configured device name.

    ``auto``: ``cuda`` when torch sees a CUDA device, else ``cpu``; ``cuda`` without one is a
    `ConfigError`; any other name torch knows (``cuda:1``) is returned as given.
    """
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r} asked for, but torch sees no CUDA device")
    torch.device(name)  # an unknown name raises here
    return name


class SectionClock:
    """Seconds per named section of a loop: ``lap(name)`` charges the time since the last lap.

    With ``profile`` on a CUDA device every lap waits for the device first, so the queued work is
    charged to the section that queued it; otherwise a lap reads the host clock only.
    """

    def __init__(self, device: torch.device, *, profile: bool = False) -> None:
        self.totals: dict[str, float] = {}
        self._sync = profile and device.type == "cuda"
        self._device = device
        self._last = time.perf_counter()

    def now(self) -> float:
        if self._sync:
            torch.cuda.synchronize(self._device)
        return time.perf_counter()

    def lap(self, name: str) -> None:
        now = self.now()
        self.totals[name] = self.totals.get(name, 0.0) + now - self._last
        self._last = now
