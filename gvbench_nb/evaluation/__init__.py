"""Evaluation over written runs: reading their tables, the bootstrap over queries and its
intervals, and the shared figures (PR curves). AP and MR themselves are ``protocol/metrics.py``."""
