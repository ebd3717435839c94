"""benchmarks/official_size.py: the stated rule's pair files, and the table of its runs."""

import official_size
import pandas as pd
import pytest

from gvbench_nb.data.sequences import frame_index, read_pairs

COLUMNS = [
    "exit_code",
    "method",
    "n_pairs",
    "wall_seconds",
    "seconds_per_pair",
    "peak_rss_mib",
    "largest_process_peak_rss_mib",
    "cache_mib",
    "store_mib",
    "load_average",
]


def check_rule(pairs, n_pairs, frames=200):
    """The docstring's rule: two query traversals against day_right, true within 2 frames, none 3-5 apart."""
    gaps = [abs(frame_index(p.query) - frame_index(p.reference)) for p in pairs]
    assert len(pairs) == len({(p.query, p.reference) for p in pairs}) == n_pairs
    assert {p.query.split("/")[0] for p in pairs} == {"night_right", "day_left"}
    assert {p.reference.split("/")[0] for p in pairs} == {"day_right"}
    assert [p.label for p in pairs] == [int(gap <= 2) for gap in gaps]
    assert not any(2 < gap < 6 for gap in gaps) and max(frame_index(p.query) for p in pairs) < frames
    assert pairs == sorted(pairs, key=lambda p: (p.query, p.reference))


@pytest.mark.real_data
def test_the_official_sizes_are_nested_draws_of_the_stated_rule(shared_data):
    root = shared_data / "gardens_point"
    sizes = {n: official_size.official_size_pairs(root, n) for n in (2000, 8000, 34400)}
    for n, pairs in sizes.items():
        check_rule(pairs, n)
        assert sum(p.label for p in pairs) / n == pytest.approx(1988 / 77648, rel=0.2)  # the candidates' share
    assert set(sizes[2000]) <= set(sizes[8000]) <= set(sizes[34400])
    assert len(official_size.official_size_pairs(root, 77648)) == 77648
    with pytest.raises(SystemExit, match="the rule has 77648"):
        official_size.official_size_pairs(root, 77649)


@pytest.mark.real_data
@pytest.mark.slow
def test_the_script_writes_the_rules_pair_files_and_a_table_of_its_runs(shared_data, tmp_path, capsys):
    options = ["--sizes", "40,80", "--methods", "orb-nn", "--frames", "20", "--out", str(tmp_path)]
    assert official_size.main(options) == 0
    files = {n: read_pairs(tmp_path / "pairs" / f"official_size_{n}.txt") for n in (40, 80)}
    for n, pairs in files.items():
        check_rule(pairs, n, frames=20)
    assert set(files[40]) <= set(files[80])
    table = pd.read_csv(tmp_path / "official_size.csv")
    assert list(table.columns) == COLUMNS
    assert table["n_pairs"].tolist() == [40, 80] and (table["exit_code"] == 0).all()
    assert (table[["wall_seconds", "peak_rss_mib", "cache_mib", "store_mib"]] > 0).all().all()
    assert "orb-nn: the six official sequences (175324 pairs) in" in capsys.readouterr().out
