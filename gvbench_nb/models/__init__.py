"""Readable PyTorch models written for gvbench_nb (one file a model)."""
