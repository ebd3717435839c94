"""gvbench-nb: geometric verification of loop closures, benchmarked as in GV-Bench.

Stages (one function each): ``config.prepare_sequence`` -> ``image_features.extract_features``
-> ``pair_matching.match_and_verify`` -> ``method_runs.pairs_table`` -> ``scoring.evaluate``.
"""

__version__ = "0.1.0"
