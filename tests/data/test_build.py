"""Building sequences by retrieval + a label rule on tiny made-up traversals whose local
descriptors go straight into the feature cache: "the same frame comes first" is the known answer."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from gvbench_nb.data import build_inputs, sequences
from gvbench_nb.runner import image_features, sequence_build
from gvbench_nb.studies import build_sequence as build_study

NUM_FRAMES = 8
DIM = 16
NIGHT_DAY = {"query_folder": "night", "reference_folders": ["day"]}
WORD_CENTRES = 3.0 * np.random.default_rng(99).normal(size=(4, DIM))


def place_descriptors(frame: int, rng: np.random.Generator, design: str, count: int = 32) -> np.ndarray:
    """Place ``frame``'s descriptors, alike in every traversal. "vlad": 4 shared words, offset per
    place (residuals tell places apart); "bow": a centre only this place has."""
    place = np.random.default_rng(1000 + frame)
    if design == "vlad":
        words = np.arange(count) % len(WORD_CENTRES)
        rows = WORD_CENTRES[words] + 0.5 * place.normal(size=(len(WORD_CENTRES), DIM))[words]
    else:
        rows = np.repeat(place.normal(size=(1, DIM)), count, axis=0)
    return (rows + 0.02 * rng.normal(size=rows.shape)).astype(np.float32)


def make_traversals(
    root: Path, cache_dir: Path, folders: list[str], design: str = "vlad", profile: str = "repository"
) -> None:
    """Image files (tiny placeholders) and their cached local descriptors."""
    options = build_inputs.parse_options({"query_folder": "x", "reference_folders": ["y"]})
    store = image_features.feature_store(cache_dir, sequence_build.local_feature_conf(options, profile))
    rng = np.random.default_rng(7)
    with store.writer() as writer:
        for folder in folders:
            (root / folder).mkdir(parents=True, exist_ok=True)
            for frame in range(NUM_FRAMES):
                name = f"{folder}/Image{frame:03d}.png"
                cv2.imwrite(str(root / name), np.full((8, 8), 40 * frame % 255, np.uint8))
                rows = place_descriptors(frame, rng, design)
                keypoints, scores = np.zeros((len(rows), 2), np.float32), np.ones(len(rows), np.float32)
                features = {
                    "keypoints": keypoints,
                    "scores": scores,
                    "descriptors": rows,
                    "image_size": np.array([8, 8]),
                }
                writer.put(image_features.image_key(root, name), features, {"seconds": 0.0})


def write_params(tmp_path: Path, **options: object) -> Path:
    words = {"vlad": {"num_words": 4}, "bow": {"num_words": 4}}
    builder_options = NIGHT_DAY | {"descriptor": "vlad", "descriptor_options": words, "top_n": 3}
    builder_options |= {"label_rule": "frame_tolerance", "label_params": {"k": 1}, **options}
    params = {"sequence": "tiny", "pairs_builder": "retrieval", "builder_options": builder_options, "seed": 0}
    params |= {"image_root": str(tmp_path / "images"), "pairs": str(tmp_path / "out" / "pairs.txt")}
    params |= {"methods": ["sift-nn"], "profile": "repository", "output_dir": str(tmp_path / "out")}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(params | {"cache_dir": str(tmp_path / "cache")}))
    return path


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    make_traversals(tmp_path / "images", tmp_path / "cache", ["night", "day", "dusk"])
    return tmp_path


def built(tmp_path: Path, **options: object) -> dict:
    return sequence_build.build_sequence(
        sequence_build.load_build_params(write_params(tmp_path, **options)), progress=False
    )


def test_pair_file_round_trips_card_counts_match_and_recall_curves_reach_the_card(tiny: Path) -> None:
    params = sequence_build.load_build_params(write_params(tiny))
    card = sequence_build.build_sequence(params, progress=False)
    curves = build_study.recall_curves(params, ["vlad", "bow"], progress=False)
    assert set(curves["descriptor"]) == {"vlad", "bow"} and curves["k"].max() == 3
    for _, group in curves.groupby("descriptor"):
        assert np.all(np.diff(group["recall"]) >= 0)
    vlad = curves[curves["descriptor"] == "vlad"].set_index("k")["recall"]
    assert vlad[1] == card["retrieval_recall"]["recall@1"] and vlad[3] == card["retrieval_recall"]["recall@3"]
    pairs = sequences.read_pairs(card["files"]["pairs"])
    candidates = pd.read_csv(card["files"]["candidates"])
    assert len(pairs) == NUM_FRAMES * 3 == len(candidates)
    assert [(p.query, p.reference, p.label) for p in pairs] == list(
        zip(candidates["query"], candidates["reference"], candidates["label"])
    )
    summary = sequences.summarize(sequences.Sequence("tiny", tiny / "images", pairs))
    assert card["counts"] == {k: v for k, v in summary.items() if k != "sequence"}
    assert json.loads(Path(card["files"]["card_json"]).read_text())["counts"] == card["counts"]
    assert f"| pairs | {len(pairs)} |" in Path(card["files"]["card_markdown"]).read_text()
    sequence_build.check_card(card["files"]["pairs"])
    # an edited pair file no longer matches its card
    lines = Path(card["files"]["pairs"]).read_text().splitlines()
    Path(card["files"]["pairs"]).write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(build_inputs.BuildError, match="card counts differ"):
        sequence_build.check_card(card["files"]["pairs"])


@pytest.mark.parametrize("descriptor, num_words", [("vlad", 4), ("bow", 2 * NUM_FRAMES)])
def test_retrieval_finds_the_known_place_first(tmp_path: Path, descriptor: str, num_words: int) -> None:
    make_traversals(tmp_path / "images", tmp_path / "cache", ["night", "day"], design=descriptor)
    card = built(tmp_path, descriptor=descriptor, descriptor_options={descriptor: {"num_words": num_words}})
    assert card["descriptor_options"] == {"num_words": num_words}
    candidates = pd.read_csv(card["files"]["candidates"])
    first = candidates[candidates["rank"] == 0]
    assert [sequences.frame_index(q) for q in first["query"]] == [sequences.frame_index(r) for r in first["reference"]]
    assert card["retrieval_recall"]["recall@1"] == 1.0
    # labels are the rule |i - j| <= 1, recomputed here from the names
    expected = [
        int(abs(sequences.frame_index(q) - sequences.frame_index(r)) <= 1)
        for q, r in zip(candidates["query"], candidates["reference"])
    ]
    assert candidates["label"].tolist() == expected
    # ground truth: 2 true references at the ends of the route, 3 elsewhere
    assert card["ground_truth"]["true_references_per_query"] == pytest.approx(
        (2 * 2 + 3 * (NUM_FRAMES - 2)) / NUM_FRAMES
    )


def test_same_seed_same_sequence_other_seed_other_queries(tiny: Path) -> None:
    queries = lambda card: {p.query for p in sequences.read_pairs(card["files"]["pairs"])}
    first = built(tiny, num_queries=4)
    text, first_queries = Path(first["files"]["pairs"]).read_text(), queries(first)
    second = built(tiny, num_queries=4)
    assert Path(second["files"]["pairs"]).read_text() == text
    assert {k: v for k, v in first.items() if k != "seconds"} == {k: v for k, v in second.items() if k != "seconds"}
    assert first["counts"]["n_queries"] == 4
    params = sequence_build.load_build_params(write_params(tiny, num_queries=4))
    params["seed"] = 1
    other = sequence_build.build_sequence(params, progress=False)
    assert len(queries(other)) == 4 and queries(other) != first_queries


def test_multi_experience_candidates_come_from_every_experience(tiny: Path) -> None:
    card = built(tiny, reference_folders=["day", "dusk"], top_n=2)
    candidates = pd.read_csv(card["files"]["candidates"])
    # the same place in both experiences is the best pair: day/i and dusk/i take the two slots
    for _, group in candidates.groupby("query"):
        assert set(group["experience"]) == {"day", "dusk"}
        assert {sequences.frame_index(r) for r in group["reference"]} == {sequences.frame_index(group["query"].iloc[0])}
    assert set(card["per_experience"]) == {"day", "dusk"}
    assert all(v["n_pairs"] == NUM_FRAMES for v in card["per_experience"].values())
    pairs = sequences.read_pairs(card["files"]["pairs"])
    assert {p.reference.split("/")[0] for p in pairs} == {"day", "dusk"}
    assert card["retrieval_recall"]["recall@1"] == 1.0


def test_best_experience_table_keeps_each_query_best_pair() -> None:
    candidates = pd.DataFrame(
        [("q0", "day", "day/a", 0, 0.9, 0), ("q0", "dusk", "dusk/a", 1, 0.8, 1)]
        + [("q1", "day", "day/b", 0, 0.7, 1), ("q1", "dusk", "dusk/b", 1, 0.6, 0)],
        columns=["query", "experience", "reference", "rank", "similarity", "label"],
    )
    scores = candidates[["query", "reference"]].assign(score=[5, 40, 12, 12])
    best = build_study.best_experience_table(candidates, scores)
    assert best["experience"].tolist() == ["dusk", "day"]  # q1: a tie goes to the better rank
    assert best["label"].tolist() == [1, 1]
    with pytest.raises(build_inputs.BuildError, match="no 'score' for candidate pair q1 dusk/b"):
        build_study.best_experience_table(candidates, scores.iloc[:3])


def test_pose_labels_from_metadata_agree_with_the_sample_generator(tmp_path: Path) -> None:
    """Our pose rule on the sample's poses.csv and generator.json gives its generator's labels."""
    from gvbench_nb.data import synthetic

    root = tmp_path / "sample"
    synthetic.generate_sample(root, n_frames=8, image_size=(80, 60))
    metadata = {
        "csv": "poses.csv",
        "name": "image",
        "position": ["x", "y", "z"],
        "heading": "yaw_deg",
        "frame": "frame",
    }
    options = build_inputs.parse_options(
        {**NIGHT_DAY, "label_rule": "pose", "label_params_file": "generator.json", "metadata": metadata}
    )
    inputs = build_inputs.prepare_inputs({"image_root": str(root), "seed": 0, "profile": "repository"}, options)
    assert inputs.rule_params == {"max_distance_m": 8.0, "max_heading_deg": 40.0}
    truth = sequence_build.ground_truth(inputs)
    night, day = inputs.query.names, inputs.experiences["day"].names
    given = sequences.read_pairs(root / "pairs.txt")
    ours = [bool(truth[night.index(p.query), day.index(p.reference)]) for p in given]
    assert ours == [bool(p.label) for p in given]
    assert 0 < sum(ours) < len(ours)


@pytest.mark.parametrize(
    "options, message",
    [
        (NIGHT_DAY | {"top_nn": 3}, "'top_nn' \\(did you mean 'top_n'\\?\\)"),
        ({"query_folder": "night"}, "missing 'reference_folders'"),
        ({"query_folder": "day", "reference_folders": ["day"]}, "also a reference folder"),
        (NIGHT_DAY | {"descriptor": "gem"}, "unknown descriptor 'gem'"),
        (NIGHT_DAY | {"top_n": 0}, "top_n must be a positive integer"),
        (NIGHT_DAY | {"descriptor_options": {"num_words": 8}}, "descriptor_options maps descriptor names"),
        (NIGHT_DAY | {"label_rule": "gps"}, "unknown label_rule 'gps'"),
        (
            NIGHT_DAY | {"metadata": {"csv": "m.csv", "hed": 1}},
            "metadata: unknown key\\(s\\) 'hed' \\(did you mean 'heading'",
        ),
        (
            NIGHT_DAY | {"metadata": {"csv": "meta.csv", "heading": None}},
            r"7 image\(s\) of 'night' have no row in the metadata CSV meta.csv",
        ),
        (NIGHT_DAY | {"metadata": {"csv": "meta.csv"}}, r"missing column\(s\) \['heading'\]"),
    ],
)
def test_bad_options_and_metadata_say_what_is_wrong(tiny: Path, options: dict, message: str) -> None:
    (tiny / "images" / "meta.csv").write_text("name,x,y\nImage000.png,0,0\n")
    with pytest.raises(build_inputs.BuildError, match=message):
        build_inputs.prepare_inputs(
            {"image_root": str(tiny / "images"), "seed": 0}, build_inputs.parse_options(options)
        )


def test_cli_build_overrides_top_n_and_prints_the_card(tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from gvbench_nb import cli

    parser = argparse.ArgumentParser()
    cli.add_build_command(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["build", str(write_params(tiny)), "--top-n", "2", "--descriptor", "bow"])
    assert args.handler(args) == 0
    printed = capsys.readouterr().out
    assert "top 2 by bow" in printed and f"| pairs | {2 * NUM_FRAMES} |" in printed
    assert len(sequences.read_pairs(tiny / "out" / "pairs.txt")) == 2 * NUM_FRAMES
    args = parser.parse_args(["build", str(write_params(tiny, query_folder="nowhere"))])
    assert args.handler(args) == 2
    assert "image folder not found" in capsys.readouterr().err
