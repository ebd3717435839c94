"""Adding a matcher is one file and one method entry: the example in example_matcher.py,
registered here, runs end to end and gives what the built-in matcher of the same rule gives."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from helpers import write_params

from gvbench_nb import methods
from gvbench_nb.data import synthetic
from gvbench_nb.data.sequences import Sequence, read_pairs
from gvbench_nb.protocol import registry
from gvbench_nb.runner import method_outputs, method_runs, scoring

HERE = Path(__file__).resolve().parent


@pytest.fixture
def example_method(monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.syspath_prepend(str(HERE))  # where example_matcher.py lives, as a user's own folder would
    isolate_recipes(monkeypatch)
    # The one entry: sift-opencv-nn's extractor and the example file's class as the matcher type.
    extractor = methods.resolve_method("sift-opencv-nn", "repository")["extractor"]
    example = {"type": "example_matcher:MutualNearestNeighbourMatcher"}
    methods.register_method("sift-example", {"repository": {"extractor": extractor, "matcher": example}})
    # The built-in matcher with the same rule (mutual nearest neighbour, no ratio test), to compare.
    mutual = {"type": "nn", "mutual": True, "ratio_threshold": None, "distance_threshold": None}
    methods.register_method("sift-mutual", {"repository": {"extractor": extractor, "matcher": mutual}})
    return "sift-example"


def isolate_recipes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Registrations end with the test."""
    for profile in list(methods.RECIPES):
        monkeypatch.setitem(methods.RECIPES, profile, dict(methods.RECIPES[profile]))
    monkeypatch.setattr(methods, "REGISTERED_FROM_CODE", set())


@pytest.fixture(scope="module")
def tiny_sample(tmp_path_factory: pytest.TempPathFactory) -> Sequence:
    root = tmp_path_factory.mktemp("sample")
    synthetic.generate_sample(root, n_frames=8, image_size=(160, 120))
    return Sequence("tiny", root, read_pairs(root / "pairs.txt")).limited(12)


@pytest.mark.slow
def test_a_matcher_from_one_file_runs_end_to_end(example_method: str, tiny_sample: Sequence, tmp_path: Path) -> None:
    out, cache = tmp_path / "out", tmp_path / "cache"
    table = method_runs.run_method(tiny_sample, example_method, "repository", out, cache, device="cpu", progress=False)
    built_in = method_runs.run_method(
        tiny_sample, "sift-mutual", "repository", out, cache, device="cpu", progress=False
    )
    assert len(table) == len(tiny_sample.pairs)
    assert table["num_matches"].sum() > 0
    pd.testing.assert_series_equal(table["num_matches"], built_in["num_matches"])
    pd.testing.assert_series_equal(table["num_inliers"], built_in["num_inliers"])
    results = scoring.evaluate(out, [example_method, "sift-mutual"])
    assert list(results["method"]) == [example_method, "sift-mutual"]
    assert results["ap"].nunique() == 1
    assert (method_outputs.method_dir(out, example_method) / "pairs.csv").is_file()


def test_the_conf_records_the_example_type(example_method: str) -> None:
    conf = methods.resolve_method(example_method, "repository")
    assert conf["matcher"]["type"] == "example_matcher:MutualNearestNeighbourMatcher"
    assert conf["matcher"]["name"] == example_method
    assert not methods.is_dense(conf)


def test_a_misspelled_type_gets_one_did_you_mean(monkeypatch: pytest.MonkeyPatch) -> None:
    isolate_recipes(monkeypatch)
    extractor = methods.resolve_method("orb-nn")["extractor"]
    methods.register_method("orb-typo", {"paper": {"extractor": extractor, "matcher": {"type": "nn-hamming-typo"}}})
    with pytest.raises(
        registry.UnknownNameError,
        match="unknown matcher type 'nn-hamming-typo' in matcher conf 'orb-typo'.*Known: .*nn",
    ):
        from gvbench_nb.protocol.matching import build_matcher

        build_matcher(methods.resolve_method("orb-typo")["matcher"], "cpu")  # type: ignore[arg-type]


def test_a_taken_name_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    isolate_recipes(monkeypatch)
    with pytest.raises(ValueError, match="method name 'sift-nn' is taken"):
        methods.register_method("sift-nn", {"paper": methods.RECIPES["paper"]["sift-nn"]})


def test_a_method_registered_under_one_profile_is_refused_by_name_under_the_other(monkeypatch):
    isolate_recipes(monkeypatch)
    recipe = methods.RECIPES["paper"]["sift-nn"]
    methods.register_method(
        "sift-paper-only", {"paper": {"extractor": recipe["extractor"], "matcher": recipe["matcher"]}}
    )
    assert methods.resolve_method("sift-paper-only", "paper")["verifier"] == recipe["verifier"]
    with pytest.raises(registry.UnknownNameError, match="'sift-paper-only' has no recipe under profile 'repository'"):
        methods.resolve_method("sift-paper-only", "repository")


def test_a_stronger_verifier_reaches_the_results_by_conf(tiny_sample: Sequence, tmp_path: Path) -> None:
    import json

    out, cache = tmp_path / "out", tmp_path / "cache"
    params = {
        "profile": "repository",
        "output_dir": str(out),
        "cache_dir": str(cache),
        "device": "cpu",
        "seed": 0,
        "verifier": {"method": "USAC_MAGSAC"},
    }
    table = method_runs.run_method_of_params(params, tiny_sample, "orb-nn", progress=False)
    run = json.loads((method_outputs.method_dir(out, "orb-nn") / "run.json").read_text())
    assert run["conf"]["verifier"]["method"] == "USAC_MAGSAC"
    default = method_runs.run_method(
        tiny_sample, "orb-nn", "repository", tmp_path / "default", cache, device="cpu", progress=False
    )
    assert (table["num_matches"] == default["num_matches"]).all()  # same matches, another fit
    default_run = json.loads((method_outputs.method_dir(tmp_path / "default", "orb-nn") / "run.json").read_text())
    assert default_run["conf"]["verifier"]["method"] == "FM_RANSAC"


def test_verifier_overrides_are_checked_with_a_did_you_mean(tmp_path: Path) -> None:
    from gvbench_nb.runner import config

    path = write_params(tmp_path, methods=["orb-nn"], verifier={"threshold": 2.0})
    with pytest.raises(
        config.ParamsError, match=r"verifier: unknown key\(s\) 'threshold' \(did you mean 'threshold_px'\?\)"
    ):
        config.load_params(path)
    path = write_params(tmp_path, methods=["orb-nn"], verifier={"method": "MAGSAC"})
    with pytest.raises(config.ParamsError, match="unknown estimator 'MAGSAC'.*Did you mean 'USAC_MAGSAC'"):
        config.load_params(path)
