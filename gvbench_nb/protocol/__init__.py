"""The benchmark protocol: what the paper (the authors' hloc fork) and the GV-Bench repository compute.

Image decoding and resizing, extractors, matchers, dense-match merging, RANSAC verification
and its few-matches rule, the metrics, and the recipes of both profiles. It imports only its
libraries and itself: caches, threads, records, the CLI and plots stand around it (``runner``).
"""
