"""The benches the daemon owns at run time: their instruments opened from a bench configuration (or
simulated instruments on pseudo-terminals), the latest readings, who holds each bench, and readings
corrected by the active model."""
