from pathlib import Path

import pytest

from gvbench_nb import config
from gvbench_nb.sequences import (
    Pair, PairFileError, Sequence, frame_index, frame_tolerance_pairs, parse_pairs, read_pairs, summarize, write_pairs,
)

# Pairs, positives and queries as the GV-Bench README states them.
OFFICIAL = {
    "day": (34400, 26480, 1720), "night": (34400, 12408, 1720), "season": (34400, 30532, 1720),
    "weather": (34400, 32638, 1720), "nordland": (28124, 1776, 1407), "uacampus": (9600, 402, 640),
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
    ],
)
def test_malformed_lines_are_rejected_with_file_and_line(line, message):
    with pytest.raises(PairFileError, match=message) as error:
        parse_pairs(["ok.png ok2.png 1", line], source="pairs.txt")
    assert "pairs.txt:2" in str(error.value)


def test_duplicate_pairs_are_rejected():
    with pytest.raises(PairFileError, match=r"pairs.txt:3: duplicate pair a b \(first on line 1\)"):
        parse_pairs(["a b 1", "a c 0", "a b 1"], source="pairs.txt")


def test_sequence_images_queries_and_summary():
    sequence = Sequence("s", Path("."), [Pair("q1", "r1", 1), Pair("q1", "r2", 0), Pair("q2", "r1", 0)])
    assert sequence.images == ["q1", "r1", "r2", "q2"]
    assert sequence.queries == ["q1", "q2"]
    summary = summarize(sequence)
    assert (summary["n_pairs"], summary["n_positives"], summary["queries_without_positive"]) == (3, 1, 1)
    assert sequence.limited(2).pairs == sequence.pairs[:2]


def test_frame_tolerance_pairs_labels_follow_the_rule():
    queries = [f"night/Image{i:03d}.jpg" for i in range(200)]
    references = [f"day/Image{i:03d}.jpg" for i in range(200)]
    pairs = frame_tolerance_pairs(queries, references, tolerance=2, candidates_per_query=10, seed=1)
    assert pairs == frame_tolerance_pairs(queries, references, tolerance=2, candidates_per_query=10, seed=1)
    for pair in pairs:
        assert pair.label == int(abs(frame_index(pair.query) - frame_index(pair.reference)) <= 2)
    middle = [p for p in pairs if p.query == "night/Image030.jpg"]
    assert len(middle) == 10 and sum(p.label for p in middle) == 5
    assert sum(1 for p in middle if 2 < abs(frame_index(p.reference) - 30) <= 8) == 2


@pytest.mark.real_data
@pytest.mark.parametrize("name", sorted(OFFICIAL))
def test_official_pair_lists_load_without_images(shared_data, name):
    params = config.load_params(config.PROJECT_ROOT / "params" / f"{name}.yaml")
    sequence = config.load_sequence_pairs_only(params)
    pairs, positives, queries = OFFICIAL[name]
    summary = summarize(sequence)
    assert (summary["n_pairs"], summary["n_positives"], summary["n_queries"]) == (pairs, positives, queries)
