"""What the few-matches rule moves: AP and MR of methods on a sequence under the paper
profile with ``few_matches: zero`` (the benchmark's released code) and ``all`` (the code of
its submission period), from the same cached features.

    python benchmarks/few_matches_rule.py params/sample.yaml --methods sift-nn,disk-nn
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gvbench_nb import methods
from gvbench_nb.runner import config, method_runs, scoring, sequence_build


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/sample.yaml")
    parser.add_argument("--methods", default="sift-nn,disk-nn", help="comma-separated method names")
    parser.add_argument("--output-dir", default="outputs/few_matches_rule", help="one folder a rule is made under it")
    args = parser.parse_args()
    params = config.load_params(args.params, profile="paper")
    sequence = sequence_build.prepare_sequence(params)
    for rule in ("zero", "all"):
        out = Path(args.output_dir) / f"{params['sequence']}_{rule}"
        for method in methods.expand_methods(args.methods):
            verifier = methods.RECIPES["paper"][method]["verifier"]
            verifier["few_matches"] = rule
            table = method_runs.run_method(sequence, method, "paper", out, Path(params["cache_dir"]), progress=False)
            few = int((table["num_matches_filtered"] < verifier["min_matches"]).sum())
            print(f"few_matches={rule} {method}: {few} pairs with fewer than {verifier['min_matches']} matches")
        print(scoring.evaluate(out)[["method", "profile", "ap", "max_recall"]].to_string(index=False))


if __name__ == "__main__":
    main()
