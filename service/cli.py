"""The `tiltlab` console script's entry point; the command line itself is the package service.commands."""

from service.commands import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    raise SystemExit(main())
