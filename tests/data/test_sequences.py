from pathlib import Path

import pytest

from gvbench_nb.data.sequences import (
    Pair,
    PairFileError,
    Sequence,
    frame_index,
    frame_tolerance_pairs,
    parse_pairs,
    read_pairs,
    summarize,
    write_pairs,
)
from gvbench_nb.runner import config, sequence_build

NIGHT = [f"night/Image{i:03d}.jpg" for i in range(200)]
DAY = [f"day/Image{i:03d}.jpg" for i in range(200)]

# Pairs, positives and queries as the GV-Bench README states them.
OFFICIAL = {
    "day": (34400, 26480, 1720),
    "night": (34400, 12408, 1720),
    "season": (34400, 30532, 1720),
    "weather": (34400, 32638, 1720),
    "nordland": (28124, 1776, 1407),
    "uacampus": (9600, 402, 640),
}


def test_write_then_read_round_trips(tmp_path):
    pairs = [Pair("night/001.png", "day/003.png", 1), Pair("night/001.png", "day/040.png", 0)]
    path = write_pairs(tmp_path / "pairs.txt", pairs)
    assert path.read_text() == "night/001.png day/003.png 1\nnight/001.png day/040.png 0\n"
    assert read_pairs(path) == pairs
    assert write_pairs(tmp_path / "t.txt", [("a.png", "b.png", 0)]).read_text() == "a.png b.png 0\n"


@pytest.mark.parametrize(
    "line, message",
    [
        ("a.png b.png", "expected 3 fields"),
        ("a.png b.png 1 extra", "expected 3 fields"),
        ("a.png b.png 2", "label must be 0 or 1"),
        ("a.png b.png yes", "label must be 0 or 1"),
        ("../a.png b.png 1", "escapes the image root"),
        ("a.png x/../../b.png 1", "escapes the image root"),
        ("/etc/passwd b.png 1", "absolute path"),
        ("ok.png ok2.png 1", r"duplicate pair ok.png ok2.png \(first on line 1\)"),
    ],
)
def test_malformed_lines_are_rejected_with_file_and_line(line, message):
    with pytest.raises(PairFileError, match=message) as error:
        parse_pairs(["ok.png ok2.png 1", line], source="pairs.txt")
    assert "pairs.txt:2" in str(error.value)


def test_sequence_images_queries_and_summary():
    sequence = Sequence("s", Path("."), [Pair("q1", "r1", 1), Pair("q1", "r2", 0), Pair("q2", "r1", 0)])
    assert sequence.images == ["q1", "r1", "r2", "q2"]
    assert sequence.queries == ["q1", "q2"]
    summary = summarize(sequence)
    assert (summary["n_pairs"], summary["n_positives"], summary["queries_without_positive"]) == (3, 1, 1)
    assert sequence.limited(2).pairs == sequence.pairs[:2]


def test_frame_tolerance_pairs_labels_follow_the_rule():
    pairs = frame_tolerance_pairs(NIGHT, DAY, tolerance=2, candidates_per_query=10, seed=1)
    assert pairs == frame_tolerance_pairs(NIGHT, DAY, tolerance=2, candidates_per_query=10, seed=1)
    for pair in pairs:
        assert pair.label == int(abs(frame_index(pair.query) - frame_index(pair.reference)) <= 2)
    middle = [p for p in pairs if p.query == "night/Image030.jpg"]
    assert len(middle) == 10 and sum(p.label for p in middle) == 5
    assert sum(1 for p in middle if 2 < abs(frame_index(p.reference) - 30) <= 8) == 2


@pytest.mark.real_data
@pytest.mark.parametrize("name", sorted(OFFICIAL))
def test_official_pair_lists_load_without_images(shared_data, name):
    params = config.load_params(config.PROJECT_ROOT / "params" / f"{name}.yaml")
    sequence = Sequence(name, Path("."), read_pairs(params["pairs"]))  # the labels only, no image
    pairs, positives, queries = OFFICIAL[name]
    summary = summarize(sequence)
    assert (summary["n_pairs"], summary["n_positives"], summary["n_queries"]) == (pairs, positives, queries)


def gap(pair) -> int:
    return abs(frame_index(pair.query) - frame_index(pair.reference))


def test_negative_margin_keeps_negatives_out_of_the_ambiguous_band():
    pairs = frame_tolerance_pairs(NIGHT, DAY, tolerance=2, negative_margin=6, near_window=10, seed=3)
    assert all(pair.label == int(gap(pair) <= 2) for pair in pairs)
    assert not [p for p in pairs if 2 < gap(p) < 6]  # neither true nor false: left out
    assert all(gap(p) >= 6 for p in pairs if p.label == 0)
    for i in (30, 100, 170):
        near = [p for p in pairs if frame_index(p.query) == i and 6 <= gap(p) <= 10]
        far = [p for p in pairs if frame_index(p.query) == i and gap(p) > 40]
        assert len(near) == 2 and len(far) == 3
    # The positives do not depend on the margin.
    without = frame_tolerance_pairs(NIGHT, DAY, tolerance=2, seed=3)
    assert [p for p in pairs if p.label] == [p for p in without if p.label]
    assert any(2 < gap(p) < 6 for p in without)
    # A margin just beyond the tolerance is the rule without margin.
    assert frame_tolerance_pairs(NIGHT[:120:3], DAY[:120], negative_margin=3, seed=5) == frame_tolerance_pairs(
        NIGHT[:120:3], DAY[:120], seed=5
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"negative_margin": 2}, "negative_margin 2 must exceed tolerance 2"),
        ({"negative_margin": 9, "near_window": 8}, "near_window 8 is below the smallest negative gap 9"),
    ],
)
def test_a_margin_that_cannot_work_says_why(options, message):
    with pytest.raises(ValueError, match=message):
        frame_tolerance_pairs(["q/Image010.jpg"], ["r/Image010.jpg"], tolerance=2, **options)


@pytest.mark.real_data
@pytest.mark.parametrize(
    ("name", "folders", "smallest_negative_gap", "near_band"),
    [
        ("gardens_point", ("night_right", "day_right"), 6, (6, 10)),
        ("gardens_point_viewpoint", ("day_left", "day_right"), 6, (6, 10)),
        ("gardens_point_night_viewpoint", ("night_right", "day_left"), 6, (6, 10)),
        ("gardens_point_no_margin", ("night_right", "day_right"), 3, (3, 8)),
    ],
)
def test_gardens_point_params_build_their_rule(shared_data, tmp_path, name, folders, smallest_negative_gap, near_band):
    path = config.PROJECT_ROOT / "params" / f"{name}.yaml"
    params = config.load_params(path, pairs=str(tmp_path / "pairs.txt"), output_dir=str(tmp_path / "out"))
    sequence = sequence_build.prepare_sequence(params)
    assert params["image_root"] == str(shared_data / "gardens_point")
    assert {p.query.split("/")[0] for p in sequence.pairs} == {folders[0]}
    assert {p.reference.split("/")[0] for p in sequence.pairs} == {folders[1]}
    summary = summarize(sequence)
    assert (summary["n_queries"], summary["n_pairs"], summary["queries_without_positive"]) == (200, 2000, 0)
    assert all(p.label == int(gap(p) <= 2) for p in sequence.pairs)
    negatives = [gap(p) for p in sequence.pairs if p.label == 0]
    assert min(negatives) == smallest_negative_gap
    low, high = near_band
    assert sum(low <= g <= high for g in negatives) == 2 * 200
    written = (tmp_path / "pairs.txt").stat().st_mtime_ns
    sequence_build.prepare_sequence(params)
    assert (tmp_path / "pairs.txt").stat().st_mtime_ns == written  # unchanged pairs are not rewritten
