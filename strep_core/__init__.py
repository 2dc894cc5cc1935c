"""STREP Studio's algorithm core: sequences, readers, geometry, metrics and registration methods.

This package imports no web, viewer or cluster code (see docs/architecture in the README).
"""

from strep_core.config import RunConfig
from strep_core.errors import StrepError
from strep_core.result import Result
from strep_core.sequence import FrameSelection, Sequence

__version__ = "0.1.0"

__all__ = ["FrameSelection", "Result", "RunConfig", "Sequence", "StrepError", "__version__"]
