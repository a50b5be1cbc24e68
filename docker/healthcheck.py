#!/usr/bin/env python3
"""The image's health check: GET /health of the `tiltlab serve` running in this container, wherever it serves.

The address is worked out as `tiltlab serve` works it out itself: its command line (`--host`, `--port`,
`--ssl-certfile`) over its environment (TILTLAB_HOST, TILTLAB_PORT, a TILTLAB_CONFIG file) over the
defaults. So `docker run tiltlab --port 9000` is probed on 9000, not on the TILTLAB_PORT of the image.

    tiltlab-healthcheck            the serve process of this container (PID 1, else the first one found)
    tiltlab-healthcheck --pid N    that process (for a test outside a container)

Exit 0 when /health answers 200; 1 otherwise, with one line saying why (docker inspect shows it).
"""

from __future__ import annotations

import argparse
import os
import ssl
import sys
import urllib.error
import urllib.request
from pathlib import Path

TIMEOUT_S = 4.0


def _argv(pid: int) -> list[str]:
    raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes()
    pairs = (part.decode(errors="replace").partition("=") for part in raw.split(b"\0") if part)
    return {name: value for name, _, value in pairs}


def _serve_args(argv: list[str]) -> list[str] | None:
    """The options after `serve` of a `tiltlab serve` command line (the console script, or python -m service)."""
    for i in range(1, len(argv)):
        before = argv[i - 1]
        if argv[i] == "serve" and (Path(before).name == "tiltlab" or (before == "service" and argv[i - 2:i - 1] == ["-m"])):
            return argv[i + 1:]
    return None


def _find_serve(pid: int | None) -> tuple[int, list[str]]:
    candidates = [pid] if pid is not None else [1] + sorted(int(p.name) for p in Path("/proc").iterdir()
                                                           if p.name.isdigit() and p.name != "1")
    for candidate in candidates:
        try:
            args = _serve_args(_argv(candidate))
        except OSError:
            continue
        if args is not None:
            return candidate, args
    raise LookupError("no `tiltlab serve` runs in this container" if pid is None else f"process {pid} is not `tiltlab serve`")


def health_url(pid: int | None = None) -> str:
    """The /health address of the serve process, from its own command line and environment."""
    found, args = _find_serve(pid)
    environ = _environ(found)
    for name in [n for n in os.environ if n.startswith("TILTLAB_")]:
        del os.environ[name]
    os.environ.update({n: v for n, v in environ.items() if n.startswith("TILTLAB_")})
    from service.commands import build_parser
    from service.config import Settings

    options = build_parser().parse_args(["serve", *args])
    overrides = {name: getattr(options, name) for name in ("host", "port") if getattr(options, name, None) is not None}
    settings = Settings(**overrides)
    host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(settings.host, settings.host)
    shown = f"[{host}]" if ":" in host else host
    scheme = "https" if getattr(options, "ssl_certfile", None) else "http"
    return f"{scheme}://{shown}:{settings.port}/health"


def main() -> int:
    parser = argparse.ArgumentParser(description="GET /health of the tiltlab serve in this container")
    parser.add_argument("--pid", type=int, default=None, help="the serve process (default: found in /proc)")
    args = parser.parse_args()
    try:
        url = health_url(args.pid)
    except (LookupError, OSError, SystemExit) as exc:
        print(f"unhealthy: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - any reason is one line in docker inspect
        print(f"unhealthy: cannot work out where tiltlab serves: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    context = ssl.create_default_context()
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE  # alive is the question, not who
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S, context=context) as answer:
            status = answer.status
    except (urllib.error.URLError, OSError) as exc:
        print(f"unhealthy: {url}: {getattr(exc, 'reason', exc)}", file=sys.stderr)
        return 1
    print(f"{url}: {status}")
    return 0 if status == 200 else 1


if __name__ == "__main__":
    raise SystemExit(main())
