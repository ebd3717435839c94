"""Verifiers beyond inlier counting: estimators, homography, SUE adapter, split, learned combination,
re-scoring from cached matches."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import two_view_scene, with_outlier_matches

from gvbench_nb.data.sequences import Pair, Sequence, frame_index, frame_tolerance_pairs
from gvbench_nb.protocol.ransac import ESTIMATORS
from gvbench_nb.runner import method_outputs, method_runs
from gvbench_nb.studies import alternative_verifiers, verifier_inputs


def as_pair(points0: np.ndarray, points1: np.ndarray, n_keypoints: int = 1000) -> verifier_inputs.PairMatches:
    scores = np.ones(len(points0))
    return verifier_inputs.PairMatches(
        points0, points1, scores, np.zeros(len(points0), bool), n_keypoints, n_keypoints, (640, 480), (640, 480)
    )


def planar_scene(n_inliers: int = 120, n_outliers: int = 60, seed: int = 0):
    """Matches related by one homography (a plane seen twice), plus random outlier matches."""
    rng = np.random.default_rng(seed)
    H = np.array([[0.9, 0.05, 30.0], [-0.04, 1.05, -12.0], [1e-4, -5e-5, 1.0]])
    p0 = rng.uniform([0, 0], [640, 480], (n_inliers, 2))
    mapped = np.c_[p0, np.ones(n_inliers)] @ H.T
    p1 = mapped[:, :2] / mapped[:, 2:] + rng.normal(0, 0.3, (n_inliers, 2))
    return with_outlier_matches(rng, p0, p1, n_outliers)


def fit(pair: verifier_inputs.PairMatches, model: str, estimator: str = "FM_RANSAC") -> tuple[np.ndarray, int]:
    """The pair's inlier mask and fitted count under one GV verifier's conf, seed 0."""
    return verifier_inputs.fit_inliers(pair, alternative_verifiers.gv_conf(model, estimator, "inliers"), seed=0)


@pytest.mark.parametrize("estimator", list(ESTIMATORS))
@pytest.mark.parametrize("model,scene,stray", [("fundamental", two_view_scene, 3), ("homography", planar_scene, 2)])
def test_every_estimator_returns_the_planted_inliers(estimator, model, scene, stray):
    p0, p1, truth = scene()
    mask, fitted = fit(as_pair(p0, p1), model, estimator)
    assert fitted == len(p0)
    assert (mask & truth).sum() >= 0.95 * truth.sum()
    assert (mask & ~truth).sum() <= stray  # a random match may fall near its epipolar line


def test_homography_rejects_a_non_planar_scene_more_than_the_fundamental_matrix():
    p0, p1, truth = two_view_scene(seed=2)
    (h_mask, _), (f_mask, _) = fit(as_pair(p0, p1), "homography"), fit(as_pair(p0, p1), "fundamental")
    assert h_mask.sum() < 0.8 * f_mask.sum()


def test_normalised_scores_follow_their_definitions():
    p0, p1, truth = two_view_scene(n_inliers=80, n_outliers=20)
    pair = as_pair(p0, p1, n_keypoints=400)
    pair.num_keypoints1 = 200  # the smaller count divides
    mask, fitted = fit(pair, "fundamental", "USAC_MAGSAC")
    features = verifier_inputs.gv_features(pair, mask, fitted)
    assert features["inliers"] == mask.sum()
    assert features["inlier_ratio"] == pytest.approx(mask.sum() / 100)
    assert features["inliers_over_keypoints"] == pytest.approx(mask.sum() / 200)
    assert 0 < features["inlier_hull_area"] <= 1


def test_registry_has_every_combination_and_the_paper_verifier():
    gv = [name for name, conf in alternative_verifiers.ALTERNATIVE_VERIFIERS.items() if conf["type"] == "gv"]
    assert len(gv) == 4 * 2 * 3
    assert alternative_verifiers.ALTERNATIVE_VERIFIERS[verifier_inputs.PAPER_VERIFIER] == alternative_verifiers.gv_conf(
        "fundamental", "FM_RANSAC", "inliers"
    )
    with pytest.raises(KeyError, match="Known: "):
        alternative_verifiers.resolve_verifier("gv-F-ransack-inliers")


def test_sue_adapter_on_hand_made_positions():
    # Query a: its strong candidates agree on frames 10-12; query b's two best point 80 frames apart.
    table = pd.DataFrame(
        {
            "query": ["a"] * 4 + ["b"] * 4,
            "reference": [f"r/{frame:03d}.png" for frame in (10, 11, 12, 90, 20, 100, 21, 150)],
            "score": [50, 50, 50, 0, 50, 50, 0, 0],
        }
    )
    out = verifier_inputs.sue_pair_scores(table, slope=10.0, top_k=10)
    # a: weights 1, 1, 1, e^-10 (distance 1 at slope 10) on frames 10, 11, 12, 90, normalised.
    w = np.array([1, 1, 1, np.exp(-10.0)])
    w /= w.sum()
    frames = np.array([10, 11, 12, 90.0])
    expected = (w * (frames - (w * frames).sum()) ** 2).sum()
    assert out.loc[0, "query_sue"] == pytest.approx(expected, rel=1e-9)
    assert 2 / 3 < expected < 1  # the far, unscored candidate barely moves it
    # b: two equal weights on 20 and 100 -> variance 40^2.
    assert out.loc[4, "query_sue"] == pytest.approx(1600, rel=1e-3)
    assert out.loc[0, "score"] == pytest.approx(50 / (1 + np.sqrt(out.loc[0, "query_sue"])))
    assert out.loc[4, "score"] == pytest.approx(50 / 41, rel=1e-3)
    assert out.loc[0, "score"] > out.loc[4, "score"]  # same GV score, the consistent query ranks higher
    assert (out.loc[[3, 6, 7], "score"] == 0).all()


def test_sue_adapter_uses_only_the_top_k():
    table = pd.DataFrame(
        {"query": ["a"] * 3, "reference": ["r/000.png", "r/001.png", "r/199.png"], "score": [10, 10, 9]}
    )
    near = verifier_inputs.sue_pair_scores(table, slope=10.0, top_k=2)
    spread = verifier_inputs.sue_pair_scores(table, slope=10.0, top_k=3)
    assert near.loc[0, "query_sue"] == pytest.approx(0.25)
    assert spread.loc[0, "query_sue"] > 100


def gardens_like_pairs(n_frames: int = 200, tolerance: int = 2) -> pd.DataFrame:
    queries = [f"night_right/Image{i:03d}.jpg" for i in range(n_frames)]
    references = [f"day_right/Image{i:03d}.jpg" for i in range(n_frames)]
    pairs = frame_tolerance_pairs(queries, references, tolerance=tolerance, seed=0)
    return pd.DataFrame([(p.query, p.reference, p.label) for p in pairs], columns=["query", "reference", "label"])


@pytest.mark.parametrize("tolerance,gap", [(2, 20), (2, 4), (4, 8)])
def test_split_shares_no_place(tolerance, gap):
    pairs = gardens_like_pairs(tolerance=tolerance)
    split = verifier_inputs.place_disjoint_split(pairs, gap_frames=gap, tolerance=tolerance)

    def places(name: str) -> set[int]:
        part = pairs[split == name]
        frames = pd.concat([part["query"], part["reference"]]).map(frame_index)
        return {f + d for f in frames for d in range(-tolerance, tolerance + 1)}

    assert places("train") and places("test")
    assert not places("train") & places("test")
    assert set(split) == {"train", "test", "dropped"}
    for name in ("train", "test"):
        assert pairs.loc[split == name, "label"].nunique() == 2  # both kinds: AP is defined


def test_split_default_ranges_on_gardens_point_and_refuses_a_gap_narrower_than_a_place():
    pairs = gardens_like_pairs()
    split = verifier_inputs.place_disjoint_split(pairs)
    train = pairs[split == "train"]
    test = pairs[split == "test"]
    assert pd.concat([train["query"], train["reference"]]).map(frame_index).max() <= 89
    assert pd.concat([test["query"], test["reference"]]).map(frame_index).min() >= 110
    with pytest.raises(ValueError, match="widen the gap"):
        verifier_inputs.place_disjoint_split(gardens_like_pairs(), gap_frames=3, tolerance=2)


def test_logistic_combination_fits_predicts_and_is_deterministic():
    rng = np.random.default_rng(0)
    labels = pd.Series(np.r_[np.ones(60), np.zeros(60)].astype(int))
    features = pd.DataFrame(
        {name: rng.normal(0, 1, 120) + 1.5 * labels * (i == 0) for i, name in enumerate(verifier_inputs.FEATURES)}
    )
    conf = alternative_verifiers.resolve_verifier("learned_combination")
    first = alternative_verifiers.fit_combination(features[:80], labels[:80], conf)
    second = alternative_verifiers.fit_combination(features[:80], labels[:80], conf)
    probability = first.predict_proba(features[80:].to_numpy())
    assert probability.shape == (40, 2)
    np.testing.assert_array_equal(probability, second.predict_proba(features[80:].to_numpy()))
    coefficients = first[-1].coef_
    assert coefficients.shape == (1, len(verifier_inputs.FEATURES))
    assert np.argmax(np.abs(coefficients)) == 0  # the informative feature dominates
    with pytest.raises(ValueError, match="true and false"):
        alternative_verifiers.fit_combination(features[:10], pd.Series(np.ones(10, int)), conf)


@pytest.fixture(scope="module")
def cached_run(shared_data: Path, tmp_path_factory) -> Path:
    """sift-nn on 4 Gardens Point queries, 3 candidates each, in a temporary folder; the paper
    profile, whose verifier is the one PAPER_VERIFIER rescores with."""
    root = tmp_path_factory.mktemp("verifiers")
    pairs = []
    for q in (20, 40, 150, 170):  # the false reference stays on the query's side of the split
        for r, label in ((q, 1), (q + 1, 1), (q + 40 if q < 100 else q - 40, 0)):
            pairs.append(Pair(f"night_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label))
    sequence = Sequence("gp_verifiers", shared_data / "gardens_point", pairs)
    method_runs.run_method(sequence, "sift-nn", "paper", root / "out", root / "cache", progress=False)
    return root


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.reliability
def test_cached_matches_are_read_from_the_cache_folder_the_run_names(cached_run):
    # The run's cache folder is neither the default one nor a params file's: only its run.json names it.
    run = json.loads((method_outputs.method_dir(cached_run / "out", "sift-nn") / "run.json").read_text())
    assert run["cache_dir"] == str(cached_run / "cache")
    cached = verifier_inputs.CachedMatches(cached_run / "out", "sift-nn")
    assert cached.matches.folder.parent == cached_run / "cache" / "matches"
    best = cached.pairs.loc[cached.pairs["num_inliers"].idxmax()]
    pair = cached.pair(best["query"], best["reference"])
    assert int(pair.inlier_mask.sum()) == int(best["num_inliers"]) > 0
    cached.close()


@pytest.mark.slow
@pytest.mark.real_data
def test_rescoring_cached_matches_reproduces_the_stored_inliers(cached_run):
    cached = verifier_inputs.CachedMatches(cached_run / "out", "sift-nn", cached_run / "cache")
    conf = alternative_verifiers.resolve_verifier(verifier_inputs.PAPER_VERIFIER)
    table = verifier_inputs.gv_feature_table(cached, cached.pairs, conf, progress=False)
    np.testing.assert_array_equal(table["num_inliers"].to_numpy(), cached.pairs["num_inliers"].to_numpy())
    assert cached.pairs["num_inliers"].max() > 0  # the comparison is not 0 == 0
    # Another seed may move RANSAC's result: the equality above really uses the run's seeds.
    query, reference = cached.pairs["query"][0], cached.pairs["reference"][0]
    pair = cached.pair(query, reference)
    mask, _ = verifier_inputs.fit_inliers(pair, conf, cached.pair_seed(query, reference))
    np.testing.assert_array_equal(mask, pair.inlier_mask)
    cached.close()


@pytest.mark.real_data
def test_bench_records_conf_and_reports_a_missing_official_checkpoint(cached_run, empty_hub):
    bench = alternative_verifiers.open_bench(
        cached_run / "out",
        "sift-nn",
        cached_run / "verifiers",
        cached_run / "cache",
        progress=False,
        train_fraction=0.45,
        gap_frames=20,
        tolerance=2,
    )
    results, tables, boot = bench.evaluate(
        ["gv-F-ransac-inliers", "gv-H-magsac-inlier_ratio", "sue", "doppelgangers"], n_resamples=50
    )
    assert list(results["verifier"]) == ["gv-F-ransac-inliers", "gv-H-magsac-inlier_ratio", "sue", "doppelgangers"]
    assert (results["conf_hash"].str.len() == 10).all()
    missing = results.set_index("verifier").loc["doppelgangers"]
    assert missing["status"].startswith("unavailable") and "doppelgangers_classifier_loftr" in missing["status"]
    assert np.isnan(missing["ap"])
    ok = results[results["status"] == "ok"]
    assert (ok["ap_ci_low"] <= ok["ap"] + 1e-12).all() and (ok["ap"] <= ok["ap_ci_high"] + 1e-12).all()
    assert set(tables) == {"gv-F-ransac-inliers", "gv-H-magsac-inlier_ratio", "sue"}
    path = alternative_verifiers.write_results(results, cached_run / "verifiers")
    again = alternative_verifiers.write_results(results, cached_run / "verifiers")
    assert len(pd.read_csv(again)) == len(results) and path == again  # rewriting replaces, never duplicates
