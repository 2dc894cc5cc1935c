"""Registration methods behind one registry: see `strep_core.methods.registry`."""

from strep_core.methods.registry import (
    MethodInfo,
    MethodOutput,
    RunContext,
    available,
    base_guess,
    get,
    register,
    run,
)

__all__ = ["MethodInfo", "MethodOutput", "RunContext", "available", "base_guess", "get", "register", "run"]
