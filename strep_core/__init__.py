"""STREP Studio's algorithm core: sequences, readers, geometry, metrics and registration methods.

It imports no web, viewer or cluster code and none of the packages built on it (`strep_bench`,
`app`, `strep_cli`): docs/design/extending.md, "Layers".
"""

from strep_core.config import RunConfig
from strep_core.errors import StrepError
from strep_core.result import Result
from strep_core.sequence import FrameSelection, Sequence

__version__ = "0.1.0"

__all__ = ["FrameSelection", "Result", "RunConfig", "Sequence", "StrepError", "__version__"]
