"""Benchmark and reproduction, beside the core: they import `strep_core` and nothing above it.

`cases` (the suites and how one case runs), `tables`, `bench` (``strep bench``), `ray_runner`
(``--executor ray``), `reproduce` (``strep reproduce``: the paper's claims). matplotlib, for the
reproduction's figures, is the ``bench`` extra (`extras`).
"""
