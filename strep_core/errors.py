"""Typed errors raised by library code.

Only the CLI and the API turn these into exit codes and HTTP responses.
"""

from __future__ import annotations


class StrepError(Exception):
    """Base class of every error this library raises on purpose."""


class SequenceError(StrepError, ValueError):
    """A sequence is malformed: non-finite values, too few frames or points, mixed dimensions..."""


class FormatError(StrepError, ValueError):
    """An input file or folder cannot be read as the format it claims to be."""


class ConfigError(StrepError, ValueError):
    """A run configuration or option is invalid."""


class MethodError(StrepError, KeyError):
    """An unknown registration method was asked for."""

    def __str__(self) -> str:  # KeyError quotes its message; we want it plain.
        return str(self.args[0]) if self.args else ""


class RegistrationError(StrepError, RuntimeError):
    """A registration method failed to produce poses."""


class Cancelled(StrepError):
    """A run was cancelled through its cancel flag."""
