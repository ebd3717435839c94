"""gvbench-nb: geometric verification of loop closures, benchmarked as in GV-Bench.

Stages (one function each): ``config.prepare_sequence`` -> ``image_features.extract_features``
-> ``pair_matching.match_and_verify`` -> ``method_runs.pairs_table`` -> ``scoring.evaluate``.
"""

__version__ = "0.1.0"


class GVBenchError(Exception):
    """An error the user can cause (params, pairs, images, weights, caches, output folders): the
    command line prints its message as one sentence, without a traceback."""


def user_error_names() -> set[str]:
    """The names of every loaded ``GVBenchError`` class (a notebook's error arrives by name)."""
    found, todo = set(), [GVBenchError]
    while todo:
        for sub in todo.pop().__subclasses__():
            found.add(sub.__name__)
            todo.append(sub)
    return found
