"""Tests for the controlled condition sweep (gvbench_nb.studies.condition_sweep)."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from gvbench_nb.data import synthetic
from gvbench_nb.runner import method_outputs, method_runs
from gvbench_nb.studies import condition_sweep as cs

TINY = {"n_frames": 6, "image_size": (240, 180), "seed": 0}  # 6 queries x 6 pairs: seconds


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("sweep")


@pytest.fixture(scope="module")
def sweep(sweep_dir: Path) -> pd.DataFrame:
    return cs.run_sweep(sweep_dir, ["sift-nn"], strengths=(0.0, 1.0), threads=1, progress=False, **TINY)


def _read_png(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def test_sweep_table_has_one_row_a_cell_and_one_shared_clear_run(sweep: pd.DataFrame, sweep_dir: Path) -> None:
    assert list(sweep.columns) == cs.SWEEP_COLUMNS
    cells = sorted(zip(sweep["condition"], sweep["strength"]))
    assert cells == sorted((c, s) for c in synthetic.CONDITIONS for s in (0.0, 1.0))
    assert set(sweep["method"]) == {"sift-nn"} and set(sweep["profile"]) == {"paper"}
    n_pairs = len(pd.read_csv(sweep_dir / "images" / "pairs.csv"))
    assert (sweep["n_pairs"] == n_pairs).all()
    assert sweep[["ap", "max_recall"]].apply(lambda c: c.between(0, 1)).all().all()
    on_disk = cs.read_sweep(sweep_dir)
    on_disk = on_disk[on_disk["strength"].isin([0.0, 1.0])].reset_index(drop=True)  # other tests add cells
    pd.testing.assert_frame_equal(on_disk, sweep)
    # The clear cell is one run, shared by every condition.
    clear = sweep[sweep["strength"] == 0.0]
    assert clear[["ap", "max_recall", "n_pairs"]].nunique().max() == 1
    runs = sorted(p.name for p in (sweep_dir / "cells" / "paper").iterdir())
    assert runs == ["clear", "illumination_1.00", "season_1.00", "weather_1.00"]


def test_full_strength_degrades_illumination_and_weather(sweep: pd.DataFrame) -> None:
    by_cell = sweep.set_index(["condition", "strength"])["ap"]
    for condition in ("illumination", "weather"):
        assert by_cell[(condition, 1.0)] < by_cell[(condition, 0.0)]


def test_reference_drive_is_extracted_once(sweep: pd.DataFrame, sweep_dir: Path) -> None:
    extracted = {}
    for cell in (sweep_dir / "cells" / "paper").iterdir():
        extracted[cell.name] = method_outputs.read_run_json(cell, "sift-nn")["this_run"]["extraction"]
    n = TINY["n_frames"]
    assert extracted["clear"]["extracted"] == 2 * n  # the first run pays for the reference
    for name, counts in extracted.items():
        if name != "clear":
            assert counts == {"images": 2 * n, "cached": n, "extracted": n}, name


def test_second_call_recomputes_nothing_and_another_route_is_refused(
    sweep: pd.DataFrame, sweep_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    images = {p: p.stat().st_mtime_ns for p in (sweep_dir / "images").rglob("*.png")}

    def must_not_run(*args, **kwargs):
        raise AssertionError("run_method was called for a finished cell")

    monkeypatch.setattr(method_runs, "run_method", must_not_run)
    again = cs.run_sweep(sweep_dir, ["sift-nn"], strengths=(0.0, 1.0), threads=1, progress=False, **TINY)
    pd.testing.assert_frame_equal(again, sweep)
    assert {p: p.stat().st_mtime_ns for p in (sweep_dir / "images").rglob("*.png")} == images
    with pytest.raises(cs.SweepError, match="n_frames"):  # another route in the same folder
        cs.prepare_route(sweep_dir, seed=0, n_frames=7, image_size=TINY["image_size"])


def test_a_new_strength_runs_only_its_cell(sweep: pd.DataFrame, sweep_dir: Path) -> None:
    before = cs.read_sweep(sweep_dir)
    table = cs.run_sweep(
        sweep_dir, ["sift-nn"], conditions=("weather",), strengths=(0.0, 0.5, 1.0), threads=1, progress=False, **TINY
    )
    assert sorted(table["strength"]) == [0.0, 0.5, 1.0]
    run = method_outputs.read_run_json(sweep_dir / "cells" / "paper" / "weather_0.50", "sift-nn")
    n = TINY["n_frames"]
    assert run["this_run"]["extraction"] == {"images": 2 * n, "cached": n, "extracted": n}
    after = cs.read_sweep(sweep_dir)
    assert len(after) == len(before) + 1
    pd.testing.assert_frame_equal(after.merge(before, how="inner"), before)


def test_bad_inputs_are_refused(tmp_path: Path) -> None:
    with pytest.raises(cs.SweepError, match="sandstorm"):
        cs.run_sweep(tmp_path, ["sift-nn"], conditions=("sandstorm",), progress=False, **TINY)
    with pytest.raises(cs.SweepError, match="outside"):
        cs.run_sweep(tmp_path, ["sift-nn"], strengths=(0.0, 1.5), progress=False, **TINY)
    with pytest.raises(cs.SweepError, match="no-such-method"):
        cs.run_sweep(tmp_path, ["no-such-method"], progress=False, **TINY)
    with pytest.raises(cs.SweepError, match="disk-nn"):
        cs.method_profiles(["sift-nn", "disk-nn"], {"sift-nn": "paper"})


def test_strength_zero_and_the_reference_folder_are_the_clear_renders(sweep: pd.DataFrame, sweep_dir: Path) -> None:
    route = synthetic.make_route(TINY["seed"], TINY["n_frames"], TINY["image_size"])
    clear = route.render_query({})
    for condition in synthetic.CONDITIONS:
        zero = route.render_query({condition: 0.0})
        assert all(np.array_equal(a, b) for a, b in zip(zero, clear)), condition
        folder = sweep_dir / "images" / cs.query_folder(condition, 0.0)
        on_disk = [_read_png(p) for p in sorted(folder.glob("*.png"))]
        assert len(on_disk) == len(clear)
        assert all(np.array_equal(a, b) for a, b in zip(on_disk, clear)), condition
    # ... and a positive strength does change the images.
    strong = _read_png(sweep_dir / "images" / cs.query_folder("weather", 1.0) / "002.png")
    assert np.abs(strong.astype(np.int16) - clear[2].astype(np.int16)).mean() > 5
    # The reference folder is the clear reference drive.
    reference = route.render_reference()
    on_disk = [_read_png(p) for p in sorted((sweep_dir / "images" / "reference").glob("*.png"))]
    assert all(np.array_equal(a, b) for a, b in zip(on_disk, reference))


def test_aliasing_share_counts_look_alikes_among_top_false_pairs() -> None:
    labels = np.array([1, 1, 0, 0, 0, 0, 0, 0])
    scores = np.array([90, 10, 80, 70, 60, 5, 4, 3])
    third = 1 / 3  # of 6 false pairs: the top 2 (80 and 70)
    # Two look-alikes: one is the top false pair, the other is low.
    look_alike = np.array([0, 0, 1, 0, 0, 0, 1, 0])
    assert cs.aliasing_share(labels, scores, look_alike, top_fraction=third) == pytest.approx(0.5)
    # Look-alikes are the two hardest negatives -> 1; the two easiest -> 0.
    assert cs.aliasing_share(labels, scores, np.array([0, 0, 1, 1, 0, 0, 0, 0]), third) == 1.0
    assert cs.aliasing_share(labels, scores, np.array([0, 0, 0, 0, 0, 0, 1, 1]), third) == 0.0
    # The default top tenth of 6 false pairs is the single hardest one.
    assert cs.aliasing_share(labels, scores, look_alike) == 1.0
    assert np.isnan(cs.aliasing_share(labels, scores, np.zeros(8)))


def test_aliasing_share_splits_ties_at_the_cut_and_rejects_a_true_look_alike() -> None:
    labels = np.zeros(4, dtype=int)
    scores = np.array([0, 0, 0, 0])  # all tied: expected share = fraction of look-alikes
    look_alike = np.array([1, 0, 0, 0])
    assert cs.aliasing_share(labels, scores, look_alike, top_fraction=0.25) == pytest.approx(0.25)
    assert cs.aliasing_share(labels, scores[::-1], look_alike[::-1], top_fraction=0.5) == pytest.approx(0.25)
    scores = np.array([9, 5, 5, 1])  # top 2: the 9 (a look-alike) and one of the tied 5s (half a look-alike)
    assert cs.aliasing_share(labels, scores, np.array([1, 1, 0, 0]), top_fraction=0.5) == pytest.approx(0.75)
    with pytest.raises(cs.SweepError, match="true pair"):
        cs.aliasing_share(np.array([1, 0]), np.array([5, 3]), np.array([1, 0]))


def _hand_table(curves: dict[str, list[float]], strengths=(0.0, 0.25, 0.5, 0.75, 1.0)) -> pd.DataFrame:
    rows = [
        {"condition": condition, "strength": s, "method": "m", "profile": "paper", "max_recall": mr}
        for condition, values in curves.items()
        for s, mr in zip(strengths, values)
    ]
    return pd.DataFrame(rows).sample(frac=1.0, random_state=0)  # row order must not matter


def test_breaking_strength_interpolates_between_grid_points() -> None:
    table = _hand_table(
        {
            "illumination": [0.8, 0.7, 0.6, 0.2, 0.0],  # half = 0.4: between 0.5 (0.6) and 0.75 (0.2)
            "season": [0.8, 0.8, 0.7, 0.5, 0.45],  # never below 0.4
            "weather": [0.6, 0.1, 0.5, 0.0, 0.0],  # first drop counts, not a later recovery
        }
    )
    result = cs.breaking_strength(table).set_index("condition")
    assert result.loc["illumination", "breaking_strength"] == pytest.approx(0.5 + 0.25 * 0.2 / 0.4)
    assert result.loc["illumination", "clear_max_recall"] == pytest.approx(0.8)
    assert np.isnan(result.loc["season", "breaking_strength"])
    assert result.loc["season", "note"].startswith(cs.NOT_REACHED)
    assert result.loc["weather", "breaking_strength"] == pytest.approx(0.25 * (0.6 - 0.3) / 0.5)
    text = cs.breaking_strength_table(table)
    assert text.loc["m", "illumination"] == "0.62"
    assert text.loc["m", "season"].startswith(cs.NOT_REACHED)


def test_breaking_strength_is_undefined_when_clear_mr_is_zero_and_not_reached_at_exactly_half() -> None:
    result = cs.breaking_strength(_hand_table({"weather": [0.0, 0.0, 0.0, 0.0, 0.0]}))
    assert np.isnan(result.loc[0, "breaking_strength"])
    assert "clear MR is 0" in result.loc[0, "note"]
    result = cs.breaking_strength(_hand_table({"weather": [0.8, 0.4, 0.4, 0.3, 0.0]}))
    # 0.4 is not below half of 0.8; the curve drops below it between 0.5 and 0.75,
    # where it leaves 0.4 at 0.5 exactly.
    assert result.loc[0, "breaking_strength"] == pytest.approx(0.5)


@pytest.mark.slow
def test_render_timing_covers_clear_each_condition_and_all_three(tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import speed_bench as bench

    table = bench.print_render_time(tmp_path, n_frames=2, repeats=1, workers=1)
    assert table["setting"].tolist() == ["clear", "illumination", "season", "weather", "all three"]
    assert (table["median_seconds"] > 0).all() and (table["n_frames"] == 2).all()
    written = pd.read_csv(tmp_path / "render.csv")
    assert len(written) == 5 and set(written["workers"]) == {1}
