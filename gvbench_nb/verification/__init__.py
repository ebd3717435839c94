"""Verification: the RANSAC fit every run uses, and the verifiers compared after a run."""
