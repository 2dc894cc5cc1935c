"""The ``strep`` command line, above both the core (`strep_core`, `strep_bench`) and the service (`app`).

The only package allowed to import all of them; each command imports its part lazily
(`docs/design/extending.md`, "Layers").
"""

from strep_cli.main import main, make_parser

__all__ = ["main", "make_parser"]
