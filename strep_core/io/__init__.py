"""Readers and writers. `load_sequence` picks a reader from the path."""

from strep_core.io.deepmapping import read_deepmapping

__all__ = ["read_deepmapping"]
