"""`tiltlab serve`: run the service (database upgraded at start-up, simulated bench by default)."""

from __future__ import annotations

import argparse
import sys


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.config import get_settings

    settings = get_settings()
    host = args.host or settings.host
    port = args.port or settings.port
    app = create_app(settings)  # refuses an unusable bench scenario or database URL before anything is said
    print(f"tiltlab: serving on http://{host}:{port} (data in {settings.data_dir})", file=sys.stderr)
    uvicorn.run(app, host=host, port=port, log_level="info")
    return 0
