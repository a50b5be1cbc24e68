"""HTTP API of the tiltlab service."""
