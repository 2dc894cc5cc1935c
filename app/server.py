"""``strep serve``: run the API with uvicorn.

Binds 127.0.0.1 by default. Bound to any other address it refuses to start unless
``STREP_API_TOKEN`` is set; every API call then needs ``Authorization: Bearer <token>``.
Heavy imports stay inside `serve`: worker processes re-import this module when it is the
program's main module (``python -m app.server``).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

EXIT_REFUSED = 2


def serve(
    host: str | None = None,
    port: int | None = None,
    data_dir: str | Path | None = None,
    viewer_port: int | None = None,
) -> int:
    """Serve until interrupted; arguments left at ``None`` come from the settings (``STREP_*``).

    Returns the exit status: 0 after a clean stop, 2 when the settings are refused.
    """
    import uvicorn

    from app.core.config import InsecureSettings, Settings
    from app.main import create_app
    from app.services import DataDirBusy, check_data_dir_free

    given = {"host": host, "port": port, "data_dir": data_dir, "viewer_port": viewer_port}
    overrides = {k: v for k, v in given.items() if v is not None}
    settings = Settings(**overrides)  # type: ignore[arg-type]
    try:
        settings.check_secure()
        check_data_dir_free(settings.data_dir)
    except (InsecureSettings, DataDirBusy) as exc:
        print(f"strep serve: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level="info",
        timeout_graceful_shutdown=3,  # live event streams never end by themselves
    )
    server = uvicorn.Server(config)
    with contextlib.suppress(KeyboardInterrupt):  # uvicorn re-raises Ctrl-C after its graceful shutdown
        server.run()
    return 0 if server.started else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m app.server", description=__doc__.splitlines()[0])
    parser.add_argument("--host")
    parser.add_argument("--port", type=int)
    parser.add_argument("--data-dir", type=Path)
    parser.add_argument("--viewer-port", type=int)
    args = parser.parse_args(argv)
    return serve(host=args.host, port=args.port, data_dir=args.data_dir, viewer_port=args.viewer_port)


if __name__ == "__main__":
    sys.exit(main())
