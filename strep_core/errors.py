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


def first_lines(text: str, limit: int = 300) -> str:
    """One line of a long error text for a status or a table row: a Ray actor's "The actor is
    dead because ..." line when present, else the first non-blank line, cut to ``limit`` chars."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    because = [line for line in lines if line.startswith("The actor is dead because")]
    chosen = because[0] if because else (lines[0] if lines else "no details")
    return chosen if len(chosen) <= limit else chosen[: limit - 3] + "..."
