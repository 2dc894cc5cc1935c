"""Rerun's telemetry, switched off: writing a recording sends nothing anywhere; analytics live
in the Rerun *viewer*, and `disable_rerun_telemetry` switches off what can be switched off
before a viewer is started."""

from __future__ import annotations

import os
import subprocess
import sys


def disable_rerun_telemetry(*, write_viewer_config: bool = False) -> None:
    """Switch off Rerun's telemetry for this process and the viewers it starts.

    * ``TELEMETRY_ENABLED=false``: the SDK's OpenTelemetry tracing (set at import of this
      module too, unless already set).
    * ``write_viewer_config=True`` runs the documented opt-out ``rerun analytics disable``
      (the bundled CLI), which writes ``analytics_enabled: false`` into the user's
      ``~/.config/rerun/analytics.json``: native viewers and the web-viewer server started
      from this machine then send no usage data. Rerun 0.41 has no environment variable for
      this (its README's ``RERUN_ANALYTICS=0`` is not read by the 0.41 binary; only
      ``FORCE_RERUN_ANALYTICS`` and ``CI`` are). The wasm viewer in a browser reports from the
      browser; a page that embeds it should restrict ``connect-src`` in its CSP.
    """
    os.environ["TELEMETRY_ENABLED"] = "false"
    if write_viewer_config:
        subprocess.run(
            [sys.executable, "-m", "rerun", "analytics", "disable"],
            check=True,
            capture_output=True,
            timeout=60,
        )
