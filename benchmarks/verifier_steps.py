"""What each verifier setting moves: the repository profile's verifier, then its settings put
back one at a time to the paper's (few-matches rule zero, score filter 0.5, RANSAC confidence
0.99 and 1000 iterations, the fit in original pixels), on the same cached features and matches;
AP / MR of every step, as a markdown table.

    .venv/bin/python benchmarks/verifier_steps.py params/sample.yaml sift-nn,orb-nn,xfeat-nn [--out DIR]

Each step is a run with the params' ``verifier`` overrides (``methods.resolve_method``), so its
results sit in a folder of their own and the features are extracted once for all steps.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gvbench_nb.runner import config, method_runs, scoring, sequence_build

STEPS: list[tuple[str, dict]] = [
    ("repository", {}),
    ("few_matches=zero", {"few_matches": "zero"}),
    ("+score>0.5", {"few_matches": "zero", "min_match_score": 0.5}),
    ("+ransac 0.99/1000", {"few_matches": "zero", "min_match_score": 0.5, "confidence": 0.99, "max_iters": 1000}),
    (
        "+original px (the paper's verifier)",
        {
            "few_matches": "zero",
            "min_match_score": 0.5,
            "confidence": 0.99,
            "max_iters": 1000,
            "coordinates": "original",
        },
    ),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/sample.yaml")
    parser.add_argument("methods", help="comma-separated methods, e.g. sift-nn,orb-nn")
    parser.add_argument("--out", default="outputs/verifier_steps", help="where each step's run goes")
    args = parser.parse_args()
    params = config.load_params(args.params, profile="repository")
    sequence = sequence_build.prepare_sequence(params)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    cells: dict[tuple[str, str], str] = {}
    for index, (name, overrides) in enumerate(STEPS):
        out = Path(args.out) / f"{params['sequence']}_{index}"
        for method in methods:
            method_runs.run_method(
                sequence,
                method,
                "repository",
                out,
                Path(params["cache_dir"]),
                device=params["device"],
                seed=params["seed"],
                progress=False,
                verifier=overrides,
            )
        for row in scoring.evaluate(out, methods).itertuples():
            cells[(name, str(row.method))] = f"{row.ap:.3f} / {row.max_recall:.3f}"
    print("| verifier | " + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for name, _ in STEPS:
        print(f"| {name} | " + " | ".join(cells.get((name, m), "-") for m in methods) + " |")


if __name__ == "__main__":
    main()
