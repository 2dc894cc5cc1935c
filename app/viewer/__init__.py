"""The live viser viewer (`ViewerServer`) and the numpy scene model shared with the Rerun sink.

``from app.viewer import ViewerServer`` imports viser; ``app.viewer.scene`` does not (the
Rerun recorder uses it without pulling viser in).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.viewer.viewer import JobSink, ViewerServer, ViewerStats

__all__ = ["JobSink", "ViewerServer", "ViewerStats"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from app.viewer import viewer

        return getattr(viewer, name)
    raise AttributeError(f"module 'app.viewer' has no attribute {name!r}")
