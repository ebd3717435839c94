"""gvbench-nb: geometric verification of loop closures, benchmarked as in GV-Bench.

Stages (one function each): ``config.prepare_sequence`` -> ``pipeline.extract_features``
-> ``pipeline.match_and_verify`` -> ``pipeline.pairs_table`` -> ``pipeline.evaluate``.
"""

__version__ = "0.1.0"
