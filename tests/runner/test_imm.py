"""imm:<name> methods: any vismatch matcher as a pair matcher of ours (a stand-in module here; the
parity tests need the opt-in environment, `make setup-imm`, and skip without it)."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import subprocess
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.runner import method_runs, pair_matching, scoring

imm = methods.imm_peer()  # benchmarks/imm.py

HAVE_VISMATCH = importlib.util.find_spec("vismatch") is not None and not isinstance(
    sys.modules.get("vismatch"), types.SimpleNamespace
)
needs_vismatch = pytest.mark.skipif(
    not HAVE_VISMATCH,
    reason="vismatch is not installed: run these in the opt-in venv (make setup-imm; "
    ".venv-imm/bin/python -m pytest tests/runner/test_imm.py)",
)

# The benchmark fork's RANSAC (GV-Bench main.py's ransac_kwargs; image-matching-models branch
# gvbench, BaseMatcher.process_matches): fundamental matrix, FM_RANSAC, 3 px, 0.95, 2000
# iterations, on the matched points in the 512x288 images the matcher saw.
FORK_VERIFIER = {
    "method": "FM_RANSAC",
    "threshold_px": 3.0,
    "confidence": 0.95,
    "max_iters": 2000,
    "coordinates": "resize_to",
    "resize_to": [512, 288],
}


@pytest.fixture
def no_vismatch(monkeypatch):
    monkeypatch.setattr(imm, "vismatch_installed", lambda: False)
    imm.available_names.cache_clear()
    yield
    imm.available_names.cache_clear()


class FakeMatcher:
    """vismatch's interface: ``_forward(img0, img1)`` on float C x H x W tensors in [0, 1]."""

    seen: list[tuple] = []

    def __init__(self, max_num_keypoints: int):
        self.max_num_keypoints = max_num_keypoints

    def _forward(self, img0, img1):
        import torch

        FakeMatcher.seen.append((tuple(img0.shape), img0.dtype, float(img0.min()), float(img0.max())))
        rng = np.random.default_rng(0)
        points0 = rng.uniform([0, 0], [500, 280], size=(60, 2)).astype(np.float32)
        points1 = points0 + np.float32([4.0, 0.0])  # a pure translation: one epipolar geometry
        points1[-10:] = rng.uniform([0, 0], [500, 280], size=(10, 2))  # outliers
        return torch.from_numpy(points0), torch.from_numpy(points1), None, None, None, None


def fake_load_image(path, resize=None, rot_angle=0):
    """vismatch's loader's interface: a float C x H x W tensor in [0, 1], resized to ``resize`` (H, W)."""
    import torch

    image = torch.from_numpy(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255
    return torch.nn.functional.interpolate(image[None], size=resize, mode="bilinear", antialias=True)[0]


@pytest.fixture
def fake_vismatch(monkeypatch):
    module = types.ModuleType("vismatch")
    module.__spec__ = importlib.machinery.ModuleSpec("vismatch", None)
    module.available_models = ["fake-nn", "sift-nn"]
    module.get_matcher = lambda name, device="cpu", max_num_keypoints=2048: FakeMatcher(max_num_keypoints)
    utils = types.ModuleType("vismatch.utils")
    utils._load_image = fake_load_image
    monkeypatch.setitem(sys.modules, "vismatch", module)
    monkeypatch.setitem(sys.modules, "vismatch.utils", utils)
    imm.available_names.cache_clear()
    FakeMatcher.seen = []
    yield module
    imm.available_names.cache_clear()


def test_imm_methods_resolve_as_dense_pair_matchers(no_vismatch):
    conf = methods.resolve_method("imm:sift-nn", "paper")
    assert conf["extractor"] is None and conf["matcher"]["dense"]
    assert conf["matcher"]["type"] == "benchmarks.imm:ImmPairMatcher" and conf["matcher"]["vismatch_name"] == "sift-nn"
    assert conf["matcher"]["resize_to"] == [512, 288] and conf["paper_name"] == "vismatch sift-nn"
    assert methods.required_checkpoints("imm:sift-nn") == []
    assert methods.expand_methods("sift-nn, imm:orb-nn") == ["sift-nn", "imm:orb-nn"]
    with pytest.raises(imm.ImmUnavailableError, match="names no matcher"):
        methods.expand_methods("imm:")


def test_missing_vismatch_fails_before_any_work_saying_what_to_install(no_vismatch, tmp_path):
    with pytest.raises(imm.ImmUnavailableError, match=r"not installed.*make setup-imm"):
        methods.require("imm:sift-nn")
    sequence = Sequence("s", tmp_path, [Pair("a.png", "b.png", 1)])  # no images: nothing may be read
    with pytest.raises(imm.ImmUnavailableError, match="make setup-imm"):
        method_runs.run_method(sequence, "imm:sift-nn", "paper", tmp_path / "out", tmp_path / "cache", progress=False)
    assert not (tmp_path / "out").exists()


def test_methods_points_to_the_opt_in_venv_not_to_pip_and_has_a_description(no_vismatch, capsys):
    from gvbench_nb import cli

    assert cli.main(["methods"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    # pip install vismatch would replace the default venv's torch and kornia pins.
    assert "pip install" not in last and "make setup-imm" in last
    assert "`.venv-imm/bin/python -m gvbench_nb ...`" in last
    with pytest.raises(SystemExit):
        cli.main(["methods", "--help"])
    assert "List every registered method" in " ".join(capsys.readouterr().out.split())


def test_unknown_vismatch_name_is_one_sentence_with_a_suggestion(fake_vismatch):
    with pytest.raises(imm.ImmUnavailableError, match=r"no matcher 'sift-n'.*Did you mean 'imm:sift-nn'"):
        methods.expand_methods(["imm:sift-n"])


def test_weights_vismatch_loads_are_checked_and_named(fake_vismatch, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    fake_vismatch.available_models.append("disk-lightglue")
    from gvbench_nb.protocol.weights import MissingWeightsError

    with pytest.raises(MissingWeightsError, match=r"depth-save.pth, disk_lightglue_v0-1_arxiv.pth in .*checkpoints"):
        imm.require("imm:disk-lightglue")
    imm.require("imm:sift-nn")  # OpenCV's: nothing to check
    folder = tmp_path / "torch" / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / "disk_lightglue_v0-1_arxiv-pth").write_bytes(b"weights")
    (folder / "depth-save.pth").write_bytes(b"weights")
    assert imm.link_local_weights()["disk_lightglue_v0-1_arxiv.pth"].startswith("copied")
    imm.require("imm:disk-lightglue")
    rows = {row["method"]: row for row in imm.method_rows()}
    assert rows["imm:sift-nn"]["available"] is True and rows["imm:fake-nn"]["available"] == "unknown"


def test_xfeat_weights_are_linked_into_a_hub_snapshot_vismatch_finds(fake_vismatch, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf"))
    fake_vismatch.available_models.append("xfeat")
    from gvbench_nb.protocol.weights import MissingWeightsError

    with pytest.raises(
        MissingWeightsError, match=r"xfeat.pt in a HuggingFace snapshot of vismatch/xfeat.*weights --link"
    ):
        imm.require("imm:xfeat")
    folder = tmp_path / "torch" / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / "xfeat.pt").write_bytes(b"xfeat weights")
    assert imm.link_local_weights()["vismatch/xfeat/xfeat.pt"].startswith("linked")
    imm.require("imm:xfeat")
    # huggingface_hub's cache layout: refs/main names the snapshot folder holding the file.
    storage = tmp_path / "hf" / "models--vismatch--xfeat"
    revision = (storage / "refs" / "main").read_text()
    assert (storage / "snapshots" / revision / "xfeat.pt").read_bytes() == b"xfeat weights"
    assert imm.link_local_weights()["vismatch/xfeat/xfeat.pt"] == "present"


@needs_vismatch
@pytest.mark.slow
def test_imm_xfeat_builds_offline_from_the_linked_weights_without_the_hub_banner(tmp_path):
    if not (imm.checkpoints_dir() / "xfeat.pt").is_file():
        pytest.skip(f"xfeat.pt is not in {imm.checkpoints_dir()}: run `python -m gvbench_nb weights --link`")
    probe = (
        "import numpy as np\n"
        "from gvbench_nb import methods\n"
        "imm = methods.imm_peer()\n"
        "print(imm.link_local_weights()['vismatch/xfeat/xfeat.pt'])\n"
        "matcher = imm.ImmPairMatcher(methods.resolve_method('imm:xfeat', 'repository')['matcher'], 'cpu')\n"
        "image = np.random.default_rng(0).integers(0, 255, (288, 512, 3), dtype=np.uint8)\n"
        "print('matches', len(matcher(image, image)[0]))\n"
        "imm.ImmPairMatcher(methods.resolve_method('imm:sift-nn', 'repository')['matcher'], 'cpu')\n"
    )
    # Offline: huggingface_hub answers from its cache only (no host is asked).
    environment = {**os.environ, "HF_HUB_CACHE": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1"}
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=environment, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("linked") and "matches " in done.stdout
    assert int(done.stdout.split("matches ")[1].split()[0]) > 100
    assert "HF repo" not in done.stdout + done.stderr and "!!!!" not in done.stdout


def fake_sequence(tmp_path: Path) -> Sequence:
    rng = np.random.default_rng(1)
    for name in ("q.png", "r.png", "s.png"):
        cv2.imwrite(str(tmp_path / name), rng.integers(0, 255, (540, 960, 3), dtype=np.uint8))
    return Sequence("fake", tmp_path, [Pair("q.png", "r.png", 1), Pair("q.png", "s.png", 0)])


def test_pipeline_runs_an_imm_matcher_cached_per_pair(fake_vismatch, tmp_path):
    sequence = fake_sequence(tmp_path)
    conf = methods.resolve_method("imm:fake-nn", "paper")
    conf["verifier"].update(FORK_VERIFIER)
    counts = pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", progress=False)
    assert counts == {"pairs": 2, "cached": 0, "matched": 2}
    # vismatch's own loader made the 512x288 RGB image the matcher saw: float C x H x W in [0, 1].
    shape, dtype, low, high = FakeMatcher.seen[0]
    assert shape == (3, 288, 512) and str(dtype) == "torch.float32" and 0.0 <= low < high <= 1.0
    table = method_runs.pairs_table(sequence, conf, tmp_path / "cache", seed=0)
    assert table["num_matches"].tolist() == [60, 60]
    assert (table["num_inliers"] < 60).all()
    # Stored points are in original pixels: x scaled by 960 / 512, with pixel centres kept.
    store = pair_matching.match_store(tmp_path / "cache", conf)
    entry = store.read(pair_matching.pair_key(sequence.image_root, "q.png", "r.png", 0))
    assert entry["inlier_mask"][:50].all()  # every planted match
    rng = np.random.default_rng(0)
    expected = rng.uniform([0, 0], [500, 280], size=(60, 2)).astype(np.float32)
    np.testing.assert_allclose(entry["points0"], (expected + 0.5) * [960 / 512, 540 / 288] - 0.5, rtol=1e-5)
    # A rerun resumes (nothing matched); a changed matcher conf recomputes.
    again = pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", progress=False)
    assert again == {"pairs": 2, "cached": 2, "matched": 0}
    conf["matcher"]["max_num_keypoints"] = 1024
    changed = pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", progress=False)
    assert changed == {"pairs": 2, "cached": 0, "matched": 2}


def test_run_method_writes_imm_rows_labelled_as_such(fake_vismatch, tmp_path):
    sequence = fake_sequence(tmp_path)
    table = method_runs.run_method(
        sequence, "imm:fake-nn", "paper", tmp_path / "out", tmp_path / "cache", progress=False
    )
    assert set(table["method"]) == {"imm:fake-nn"}
    results = scoring.evaluate(tmp_path / "out")
    assert results["method"].tolist() == ["imm:fake-nn"]
    assert results["paper_name"].tolist() == ["vismatch fake-nn"]
    from gvbench_nb.studies import results_table, runtime_vs_mr, verifier_inputs

    assert "resized to 512x288" in runtime_vs_mr.run_description(tmp_path / "out", ["imm:fake-nn"], tmp_path / "cache")
    joined = results_table.join_paper_table(results, results_table.load_paper_table(Path("/nonexistent.csv")))
    assert results_table.results_table(joined).index.tolist() == [("imm:fake-nn (vismatch fake-nn)", "paper")]
    lines = verifier_inputs.match_lines(tmp_path / "out", "imm:fake-nn", "q.png", "r.png", tmp_path / "cache")
    assert lines["points0"].shape == (60, 2) and lines["inlier_mask"].sum() == table["num_inliers"].iloc[0]


# ------------------------------------------------------------- needs vismatch --
def gardens_point_pairs(shared_data: Path) -> Sequence:
    """Day-left and night-right queries against day-right references: true neighbours, a near
    and a far negative (vismatch's sift-nn at 512x288 finds about 10-30 inliers on these)."""
    pairs = []
    for folder in ("day_left", "night_right"):
        for q in (20, 75, 140):
            for r, label in ((q, 1), (q + 1, 1), (q + 5, 0), ((q + 60) % 200, 0)):
                pairs.append(Pair(f"{folder}/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label))
    return Sequence("gp_imm", shared_data / "gardens_point", pairs)


def fork_ransac(matched0: np.ndarray, matched1: np.ndarray) -> tuple:
    """The fork's RANSAC step (BaseMatcher.process_matches, branch gvbench), from its published code;
    vismatch 1.4.0 itself fits a homography (USAC_MAGSAC, 0.995) instead."""
    if len(matched0) < 8:
        return None, matched0, matched1
    F, mask = cv2.findFundamentalMat(matched0, matched1, cv2.FM_RANSAC, 3, 0.95, 2000)
    mask = mask[:, 0].astype(bool)
    return F, matched0[mask], matched1[mask]


@needs_vismatch
@pytest.mark.real_data
def test_imm_sift_nn_inliers_equal_vismatch_num_inliers_under_the_fork_settings(shared_data, tmp_path):
    from vismatch import get_matcher

    sequence = gardens_point_pairs(shared_data)
    conf = methods.resolve_method("imm:sift-nn", "paper")
    conf["verifier"].update(FORK_VERIFIER)
    pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", progress=False)
    ours = method_runs.pairs_table(sequence, conf, tmp_path / "cache", seed=0)

    theirs = get_matcher("sift-nn", device="cpu", max_num_keypoints=2048)
    theirs.compute_ransac = fork_ransac
    compared = 0
    for pair, (_, row) in zip(sequence.pairs, ours.iterrows()):
        # vismatch's own forward on the images its own loader makes (512x288 RGB, float).
        result = theirs(
            *(theirs.load_image(sequence.image_root / name, resize=(288, 512)) for name in (pair.query, pair.reference))
        )
        assert row["num_matches"] == len(result["matched_kpts0"]), pair
        if len(result["matched_kpts0"]) < 8:
            continue  # the fork counts every match as an inlier there; our verifier's rule is a profile option
        assert row["num_inliers"] == result["num_inliers"], pair
        compared += 1
    assert compared >= 16
    assert ours["num_inliers"].max() >= 20  # agreement beyond near-empty pairs


@pytest.mark.real_data
def test_peer_bench_gives_vismatch_the_pairs_and_image_size_of_our_profile(shared_data, tmp_path, monkeypatch):
    import peer_vismatch

    from gvbench_nb.runner import config, sequence_build

    monkeypatch.setenv("GVBENCH_DATA", str(shared_data))
    params = config.load_params(
        Path(__file__).resolve().parents[2] / "params" / "gardens_point.yaml",
        limit=7,
        profile="repository",
        output_dir=str(tmp_path / "out"),
    )
    params["pairs"] = str(tmp_path / "pairs.txt")
    sequence = sequence_build.prepare_sequence(params)
    assert peer_vismatch.peer_image_size(params, "sift-nn", sequence) == (288, 512)  # 960x540, longest side 512
    assert peer_vismatch.peer_image_size(params, "imm:sift-nn", sequence) == (288, 512)  # resize_to
    peer_vismatch.write_pair_file(sequence, tmp_path / "peer.txt")
    lines = (tmp_path / "peer.txt").read_text().splitlines()
    assert lines == [f"{p.query} {p.reference} {p.label}" for p in sequence.pairs] and len(lines) == 7
