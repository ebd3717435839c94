"""Analyses that run their own experiments (the synthetic condition sweep)."""
