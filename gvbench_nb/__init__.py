"""gvbench-nb: geometric verification of loop closures, benchmarked as in GV-Bench.

Stages (one function each): ``config.prepare_sequence`` -> ``image_features.extract_features``
-> ``pair_matching.match_and_verify`` -> ``method_runs.pairs_table`` -> ``scoring.evaluate``.
"""

__version__ = "0.1.0"


class GVBenchError(Exception):
    """An error the user can cause (params, pairs, images, weights, caches, output folders): the
    command line prints its message as one sentence, without a traceback."""

    exit_code = 2
