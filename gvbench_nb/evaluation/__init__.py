"""Evaluation: AP and max recall, results tables and the bootstrap, read from written results."""
