"""Registration methods behind one table: the interface in `strep_core.methods.base`, the
built-in methods in `classical` and `learned` (imported here, which adds them to the table).
The runner that runs any of them is `strep_core.runner`."""

from strep_core.methods import classical, learned  # noqa: F401 - adds the built-in methods
from strep_core.methods.base import MethodInfo, MethodOutput, RunContext, available, get, method

__all__ = ["MethodInfo", "MethodOutput", "RunContext", "available", "get", "method"]
