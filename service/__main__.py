"""`python -m service`: the same command line as the `tiltlab` script."""

from service.cli import main

raise SystemExit(main())
