"""The `tiltlab` console script's entry point (pyproject names `service.cli:main`); the command line
itself is service.commands."""

from service.commands import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    raise SystemExit(main())
