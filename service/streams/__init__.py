"""Live streams to clients (WebSocket): a bench's readings, a calibration job's progress."""
