"""Serial instruments of the bench: byte codecs, port transport, drivers per role, simulated
firmware."""
