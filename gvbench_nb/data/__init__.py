"""Sequences and their data: pair lists, a built sequence's inputs, retrieval, synthetic routes, fetching."""
