"""Sequences and their data: pair lists, images, pair builders, retrieval, synthetic routes, fetching."""
