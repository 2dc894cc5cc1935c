"""Optional extras of the benchmark: a one-line error naming the extra when one is missing."""

from __future__ import annotations

from typing import Any

from strep_core.errors import ConfigError


class MissingExtra(ConfigError):
    """An optional dependency of the asked-for command is not installed."""


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (files only, no display)."""
    try:
        import matplotlib
    except ImportError as exc:
        raise MissingExtra(
            "strep reproduce draws its figures with matplotlib, an optional extra: pip install 'strep-studio[bench]'"
        ) from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
