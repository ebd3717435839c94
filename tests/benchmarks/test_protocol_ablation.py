"""The protocol ablation changes exactly the step it names, and puts it back."""

from __future__ import annotations

import copy

import pandas as pd
import protocol_ablation
import pytest

from gvbench_nb import methods


@pytest.mark.parametrize(
    "variant, method, part, key, value",
    [
        ("ratio-on-rows", "sift-nn", "matcher", "ratio_test_on", "rows"),
        ("float32-storage", "disk-nn", "extractor", "store_float16", False),
        ("few-matches-all", "orb-nn", "verifier", "few_matches", "all"),
        ("no-resize-max", "disk-nn", "extractor", "resize_max", None),
    ],
)
def test_each_variant_changes_one_key_of_the_paper_conf_and_restores_it(variant, method, part, key, value):
    before = methods.resolve_method(method, "paper")
    tables = copy.deepcopy(methods.RECIPES)
    with protocol_ablation.VARIANTS[variant](method) as ran:
        during = methods.resolve_method(ran, "paper")
    assert during[part][key] == value != before[part].get(key, "rows_and_columns")
    changed = [
        (name, k)
        for name in ("extractor", "matcher", "verifier")
        for k in set(before[name] or {}) | set(during[name] or {})
        if (before[name] or {}).get(k) != (during[name] or {}).get(k)
    ]
    assert changed == [(part, key)]
    assert tables == methods.RECIPES
    assert methods.resolve_method(method, "paper") == before


def test_variants_that_do_not_apply_say_why():
    assert protocol_ablation.applies("ratio-on-rows", "aliked-nn", 960) == "no ratio test in its matcher"
    assert protocol_ablation.applies("opencv-sift", "disk-nn", 960) == "SIFT only"
    assert protocol_ablation.applies("no-resize-max", "disk-nn", 960).startswith("not exercised")
    assert protocol_ablation.applies("no-resize-max", "disk-nn", 2000) is None
    assert protocol_ablation.applies("ratio-on-rows", "orb-nn", 960) is None


@pytest.mark.shared_outputs  # renders params/sample.yaml's images into outputs/sample
@pytest.mark.slow
def test_ablation_on_sample_writes_one_row_a_variant(tmp_path, capsys):
    options = ["--methods", "sift-nn", "--variants", "paper,ratio-on-rows,no-resize-max", "--limit", "60"]
    folders = ["--output-dir", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")]
    assert protocol_ablation.main(["params/sample.yaml", *options, *folders]) == 0
    frame = pd.read_csv(tmp_path / "out" / "sample" / "ablation.csv")
    assert frame["variant"].tolist() == ["paper", "ratio-on-rows", "no-resize-max"]
    paper, rows = frame.iloc[0], frame.iloc[1]
    assert paper["ap_change"] == 0 and paper["n_pairs"] == 60
    # The one-way reading keeps more matches than hloc's two-way test.
    assert rows["mean_matches"] > paper["mean_matches"]
    assert frame.iloc[2]["not_run"] == "DISK only"
