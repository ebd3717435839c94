"""What each step of the paper's chain moves: AP and MR of methods under the paper profile,
then with one step at a time put back to the reading it corrects, on the same pairs.

Variants (each changes one conf key, so it gets its own cache and match folders):

- ``paper``: the profile as it runs (hloc's chain).
- ``ratio-on-rows``: the Lowe ratio test on the rows only, then the mutual check
  (``ratio_test_on: rows``), instead of hloc's rows and columns; NN methods with a ratio test.
- ``float32-storage``: features kept as float32 instead of hloc's float16 (``store_float16``).
- ``few-matches-all``: pairs with fewer than 8 matches or no model score all their matches
  (``few_matches: all``) instead of 0.
- ``opencv-sift`` (sift-nn only): OpenCV's SIFT under the same settings (the ``sift-opencv-nn``
  method) instead of COLMAP's.
- ``no-resize-max`` (DISK only): the input never shrunk, instead of shrunk above 1600 px; it
  moves nothing on images at most 1600 px wide, and is then reported as not exercised.

    python benchmarks/protocol_ablation.py params/sample.yaml --methods sift-nn,orb-nn,disk-nn

Writes ``<output-dir>/<sequence>/ablation.csv`` (one row a method and variant, with the AP and
MR change from ``paper``) and prints it.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pandas as pd
from PIL import Image

from gvbench_nb import methods
from gvbench_nb.runner import config, method_runs, scoring, sequence_build

Patch = Callable[[str], "contextlib.AbstractContextManager[str]"]


@contextlib.contextmanager
def _patched(method: str, part: str, changes: dict[str, Any]) -> Iterator[str]:
    """``method``'s paper recipe with ``changes`` in one part (extractor, matcher or verifier)."""
    recipe = methods.RECIPES["paper"][method]
    saved = copy.deepcopy(recipe[part])
    recipe[part].update(changes)
    try:
        yield method
    finally:
        recipe[part] = saved


@contextlib.contextmanager
def paper(method: str) -> Iterator[str]:
    yield method


def ratio_on_rows(method: str) -> contextlib.AbstractContextManager[str]:
    return _patched(method, "matcher", {"ratio_test_on": "rows"})


def float32_storage(method: str) -> contextlib.AbstractContextManager[str]:
    return _patched(method, "extractor", {"store_float16": False})


def few_matches_all(method: str) -> contextlib.AbstractContextManager[str]:
    return _patched(method, "verifier", {"few_matches": "all"})


@contextlib.contextmanager
def opencv_sift(method: str) -> Iterator[str]:
    yield "sift-opencv-nn"


def no_resize_max(method: str) -> contextlib.AbstractContextManager[str]:
    return _patched(method, "extractor", {"resize_max": None})


VARIANTS: dict[str, Patch] = {
    "paper": paper,
    "ratio-on-rows": ratio_on_rows,
    "float32-storage": float32_storage,
    "few-matches-all": few_matches_all,
    "opencv-sift": opencv_sift,
    "no-resize-max": no_resize_max,
}


def applies(variant: str, method: str, largest_side: int) -> str | None:
    """Why ``variant`` does not apply to ``method`` on these images, or None when it does."""
    matcher = methods.RECIPES["paper"][method]["matcher"]
    extractor = methods.RECIPES["paper"][method]["extractor"]
    if variant == "ratio-on-rows" and not (matcher["type"] == "nn" and matcher.get("ratio_threshold")):
        return "no ratio test in its matcher"
    if variant == "float32-storage" and extractor is None:
        return "no stored features"
    if variant == "opencv-sift" and method != "sift-nn":
        return "SIFT only"
    if variant == "no-resize-max":
        if extractor is None or extractor["type"] != "kornia_disk":
            return "DISK only"
        if largest_side <= extractor["resize_max"]:
            return f"not exercised: no image above {extractor['resize_max']} px"
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/sample.yaml")
    parser.add_argument("--methods", default="sift-nn,orb-nn,disk-nn", help="comma-separated method names")
    parser.add_argument(
        "--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)} (default all)"
    )
    parser.add_argument("--output-dir", default="outputs/protocol_ablation", help="a folder a sequence under it")
    parser.add_argument("--cache-dir", default=None, help="feature cache (default: the params file's)")
    parser.add_argument("--limit", type=int, default=None, help="the first N pairs only (default every pair)")
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    params = config.load_params(args.params, profile="paper", limit=args.limit, cache_dir=args.cache_dir)
    sequence = sequence_build.prepare_sequence(params)
    largest_side = max(max(Image.open(sequence.image_root / name).size) for name in sequence.images)
    out = Path(args.output_dir) / params["sequence"]
    rows: list[dict[str, Any]] = []
    for method in methods.expand_methods(args.methods):
        for variant in variants:
            reason = applies(variant, method, largest_side)
            if reason:
                rows.append({"method": method, "variant": variant, "not_run": reason})
                continue
            with VARIANTS[variant](method) as ran:
                folder = out / variant
                table = method_runs.run_method(sequence, ran, "paper", folder, Path(params["cache_dir"]), progress=True)
                result = scoring.evaluate(folder, [ran], write=False).iloc[0]
            rows.append(
                {
                    "method": method,
                    "variant": variant,
                    "ran": ran,
                    "n_pairs": len(table),
                    "mean_matches": round(float(table["num_matches_filtered"].mean()), 1),
                    "pairs_under_8_matches": int((table["num_matches_filtered"] < 8).sum()),
                    "ap": round(float(result["ap"]), 3),
                    "max_recall": round(float(result["max_recall"]), 3),
                    "not_run": "",
                }
            )
    frame = pd.DataFrame(rows).convert_dtypes()
    base = frame[frame["variant"] == "paper"].set_index("method")
    for column in ("ap", "max_recall"):
        if column in frame and "paper" in variants:
            frame[f"{column}_change"] = (frame[column] - frame["method"].map(base[column])).round(3)
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "ablation.csv", index=False)
    print(frame.astype(object).where(frame.notna(), "").to_string(index=False))
    print(out / "ablation.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
