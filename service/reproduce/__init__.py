"""Reruns of the four papers' experiments on simulated benches (seed 003 on its real data), as
reports."""
