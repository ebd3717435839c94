"""The method registry: every method resolves, missing weights fail before any work,
and every method whose weights are here runs on real pairs."""

import os
from pathlib import Path

import pytest
import torch
from filelock import FileLock

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol import weights
from gvbench_nb.runner import image_features, method_runs

PAPER_METHODS = ["sift-nn", "sp-nn", "sp-sg", "disk-nn", "disk-lg", "loftr"]


@pytest.mark.parametrize("name", methods.method_names())
@pytest.mark.parametrize("profile", list(methods.RECIPES))
def test_every_method_resolves_with_its_checkpoints_known(name, profile):
    conf = methods.resolve_method(name, profile)
    assert conf["profile"] == profile and conf["method"] == name
    for checkpoint in methods.required_checkpoints(name, profile):
        assert checkpoint in weights.CHECKPOINTS


def test_the_paper_methods_and_the_modern_ones_are_registered():
    assert [m for m in methods.method_names() if methods.RECIPES["paper"][m]["in_paper"]] == PAPER_METHODS
    assert {"sp-lg", "aliked-nn", "aliked-lg", "xfeat-nn", "xfeat-lg", "orb-nn"} <= set(methods.method_names())


def test_repository_profile_changes_the_cache_identity():
    paper = methods.resolve_method("disk-lg", "paper")
    repository = methods.resolve_method("disk-lg", "repository")
    assert repository["extractor"]["resize_to"] == [512, 288]
    assert methods.conf_hash(paper["extractor"]) != methods.conf_hash(repository["extractor"])
    assert methods.conf_hash(paper["verifier"]) != methods.conf_hash(repository["verifier"])


def test_unknown_method_lists_the_valid_names():
    with pytest.raises(KeyError, match=r"unknown method 'sift-n'\. Did you mean 'sift-nn'\?.*disk-lg"):
        methods.expand_methods("sift-n")


def test_missing_weights_fail_before_any_work(empty_hub, tmp_path):
    sequence = Sequence("s", tmp_path / "images", [Pair("a.png", "b.png", 1)])
    with pytest.raises(weights.MissingWeightsError) as error:
        method_runs.run_method(sequence, "sp-sg", "paper", tmp_path / "out", tmp_path / "cache", progress=False)
    message = str(error.value)
    for expected in (
        "superpoint_v1.pth",
        "superglue_outdoor.pth",
        str(empty_hub / "superglue_outdoor.pth"),
        "https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superglue_outdoor.pth",
    ):
        assert expected in message
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


def test_results_lists_every_method_without_results_with_the_files_it_needs(empty_hub):
    from gvbench_nb.reporting.tables import not_run_table

    table = not_run_table({"sift-nn", "disk-nn"}).set_index("method")
    assert set(table.index) == set(methods.method_names()) - {"sift-nn", "disk-nn"}
    assert table.loc["orb-nn", "status"] == "weights present, not run"  # ORB needs no weights
    assert "`disk_lightglue_v0-1_arxiv-pth`" in table.loc["disk-lg", "status"]
    assert "`superglue_outdoor.pth` from https://" in table.loc["sp-sg", "status"]


@pytest.mark.slow
def test_loftr_loads_an_official_layout_checkpoint_strictly(empty_hub):
    from kornia.feature import LoFTR

    from gvbench_nb.protocol.matching.loftr import LoFTRMatcher

    state = {f"matcher.{k}": v for k, v in LoFTR(pretrained=None).state_dict().items()}
    empty_hub.mkdir(parents=True)
    torch.save({"state_dict": state, "epoch": 29}, empty_hub / "loftr_outdoor.ckpt")
    matcher = LoFTRMatcher(methods.resolve_method("loftr")["matcher"], torch.device("cpu"))
    assert matcher.model.coarse_matching.thr == 0.2
    del state["matcher.backbone.conv1.weight"]
    torch.save({"state_dict": state}, empty_hub / "loftr_outdoor.ckpt")
    with pytest.raises(weights.WeightsLayoutError, match="missing tensors: backbone.conv1.weight"):
        LoFTRMatcher(methods.resolve_method("loftr")["matcher"], torch.device("cpu"))


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory) -> Path:
    # One cache for the test run, shared by pytest-xdist's workers (the feature store is safe for
    # several writers): methods sharing an extractor conf extract once (disk-nn, disk-lg).
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-method-cache"
    folder.mkdir(exist_ok=True)
    return folder


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.parametrize(
    "method",
    [
        m
        for m in methods.method_names()
        if not methods.required_checkpoints(m) or all(weights.is_present(c) for c in methods.required_checkpoints(m))
    ],
)
def test_available_methods_score_true_pairs_above_far_false_pairs(shared_data, shared_cache, tmp_path, method):
    pairs = []
    for q in (10, 80, 150):  # two true references and one far-apart false one a query
        for r, label in ((q, 1), (q + 1, 1), ((q + 60) % 200, 0)):
            pairs.append(Pair(f"night_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label))
    sequence = Sequence("gp_test", shared_data / "gardens_point", pairs)
    profile = "paper" if method in ("sift-nn", "orb-nn") else "repository"  # learned models at 512x288 keep CI short
    extractor = methods.resolve_method(method, profile)["extractor"]
    if extractor:  # one worker extracts what two methods share; the other waits for it, then reads it
        with FileLock(shared_cache / f"extract-{methods.conf_hash(extractor)}.lock"):
            image_features.extract_features(sequence, extractor, shared_cache, "cpu", progress=False)
    table = method_runs.run_method(sequence, method, profile, tmp_path / "out", shared_cache, progress=False)
    true_mean = table.loc[table.label == 1, "score"].mean()
    false_mean = table.loc[table.label == 0, "score"].mean()
    assert true_mean > false_mean, table[["query", "reference", "label", "score"]]
