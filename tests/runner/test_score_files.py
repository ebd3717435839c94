"""``import-scores`` and ``results --export npy``: the GV-Bench authors' .npy is built here as their
``.asset/replicate.md`` documents it (inliers as point rows or counts), on a small ``sample`` render;
the rules imported pairs obey, on eight real Gardens Point pairs (``GP8``)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import in_process_notebooks, one_sentence, run_cli, snapshot
from sklearn.metrics import average_precision_score, precision_recall_curve

from gvbench_nb import run_and_publish
from gvbench_nb.data import synthetic
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.runner import method_outputs, runs, scoring

QUERIES = [f"night/{i:03d}.png" for i in (0, 0, 1, 1, 2, 2)]
REFERENCES = [f"day/{i:03d}.png" for i in (0, 5, 1, 6, 2, 7)]
LABELS = [1, 0, 1, 0, 1, 0]
INLIERS = [40, 12, 9, 15, 30, 3]  # a false pair above a true one: MR below 1


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)


def hashes(folder: Path) -> dict[str, str]:
    """The SHA-256 of every file under ``folder``."""
    return {name: hashlib.sha256(data).hexdigest() for name, data in snapshot(folder).items()}


def run_ids(folder: Path) -> list[str]:
    return [run.name for run, _ in runs.finished_runs(folder)]


def shown_run(folder: Path, method: str) -> str:
    """The id of the run the folder shows for ``method``."""
    return method_outputs.method_dir(folder, method).parent.name


def authors_npy(path: Path, inliers_as: str = "points", **changes) -> Path:
    """An .npy as the authors' evaluation writes it (their keys; our numbers)."""
    counts = np.array(INLIERS)
    prob = counts / counts.max()
    precision, recall, thresholds = precision_recall_curve(LABELS, prob)
    rng = np.random.default_rng(0)
    values = {
        "prob": prob,
        "qImages": list(QUERIES),
        "rImages": list(REFERENCES),
        "gt": list(LABELS),
        "inliers": [rng.random((n, 4)).astype(np.float32) for n in INLIERS] if inliers_as == "points" else counts,
        "all_matches": [rng.random((n + 5, 4)).astype(np.float32) for n in INLIERS],
        "precision": precision,
        "recall": recall,
        "TH": thresholds,
        "average_precision": np.float64(average_precision_score(LABELS, prob)),
        "Max Recall": float(recall[precision == 1.0].max()),
    }
    if inliers_as == "absent":
        del values["inliers"]
    values.update(changes)
    with open(path, "wb") as handle:  # np.save(name) would add .npy to a name not ending in it
        np.save(handle, values, allow_pickle=True)
    return path


def import_scores(capsys, source: Path, method: str, folder: Path, sequence: str = "s") -> tuple[int, str, str]:
    argv = ["import-scores", str(source), "--sequence", sequence, "--method", method, "--output-dir", str(folder)]
    return run_cli(capsys, *argv)


def results_row(capsys, folder: Path, method: str) -> dict:
    code, _, err = run_cli(capsys, "results", str(folder))
    assert code == 0, err
    table = scoring.evaluate(folder, write=False).set_index("method")
    return table.loc[method].to_dict()


@pytest.mark.parametrize("inliers_as", ["points", "counts", "absent"])
def test_the_authors_npy_imports_with_their_ap_and_mr(tmp_path, capsys, inliers_as):
    source = authors_npy(tmp_path / "night_superpoint_superglue.npy", inliers_as)
    out = tmp_path / "out"
    code, said, err = import_scores(capsys, source, "sp-sg", out, "night")
    assert code == 0, err
    expected = evaluate_scores(np.array(LABELS), np.array(INLIERS, dtype=float))
    assert 0 < expected["max_recall"] < 1 and expected["ap"] < 1
    row = results_row(capsys, out, "sp-sg")
    assert (row["ap"], row["max_recall"], row["n_pairs"]) == (expected["ap"], expected["max_recall"], 6)
    assert row["profile"] == "imported" and row["paper_name"] == "SP+SG (imported)"
    assert f"the file states ap {expected['ap']:.4f}" in said
    run = method_outputs.read_run_json(out, "sp-sg")
    assert run["imported"]["sha256"] == hashlib.sha256(source.read_bytes()).hexdigest()
    assert run["imported"]["file"] == str(source) and run["sequence"] == "night"
    table = scoring.load_pairs_table(out, "sp-sg")
    assert table["query"].tolist() == QUERIES and table["reference"].tolist() == REFERENCES
    if inliers_as != "absent":
        assert table["num_inliers"].tolist() == INLIERS


class RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.mark.reliability
def test_a_npy_whose_pickle_would_run_code_is_refused_without_running_it(tmp_path, capsys):
    marker = tmp_path / "ran"
    source = authors_npy(tmp_path / "evil.npy", gt=[RunsCode(marker)] * 6)
    out = tmp_path / "out"
    code, _, err = import_scores(capsys, source, "x", out)
    assert code == 2 and "posix.system" in one_sentence(err) and "refused without running it" in err
    assert not marker.exists() and not out.exists()
    np.load(source, allow_pickle=True)  # numpy's own loader does run it: the file is what the test says
    assert marker.exists()


def test_tables_import_as_csv_with_a_header_and_as_whitespace_with_quoted_paths(tmp_path, capsys):
    scores = [0.9, 0.2, 0.35, 0.4, 0.8, 0.1]
    csv = tmp_path / "scores.csv"
    csv.write_text(
        "query,reference,label,score\n"
        + "".join(f"{q},{r},{lab},{s}\n" for q, r, lab, s in zip(QUERIES, REFERENCES, LABELS, scores))
    )
    spaced = [q.replace("night/", "night run/") for q in QUERIES]
    text = tmp_path / "scores.txt"
    text.write_text("".join(f'"{q}" {r}  {lab}\t{s}\n' for q, r, lab, s in zip(spaced, REFERENCES, LABELS, scores)))
    expected = evaluate_scores(np.array(LABELS), np.array(scores))
    for source, method in ((csv, "from-csv"), (text, "from-text")):
        code, _, err = import_scores(capsys, source, method, tmp_path / method)
        assert code == 0, err
        row = results_row(capsys, tmp_path / method, method)
        assert (row["ap"], row["max_recall"]) == (expected["ap"], expected["max_recall"])
    assert scoring.load_pairs_table(tmp_path / "from-text", "from-text")["query"].tolist() == spaced


@pytest.mark.reliability
def test_bad_score_files_are_refused_in_one_sentence_before_any_write(tmp_path, capsys):
    out = tmp_path / "out"
    bad_label = tmp_path / "bad.txt"
    bad_label.write_text("q r 2 5\nq s 0 1\n")
    short = authors_npy(tmp_path / "short.npy", gt=LABELS[:4])
    for source, words in (
        (bad_label, "bad.txt:1: label must be 0 or 1"),
        (short, "differ in length"),
        (tmp_path / "no.npy", "does not exist"),
    ):
        code, _, err = import_scores(capsys, source, "m", out)
        assert code == 2 and words in one_sentence(err), err
    assert not out.exists()


def sample_params(tmp_path: Path, **changes) -> Path:
    root = tmp_path / "sample"
    synthetic.generate_sample(root, n_frames=8, image_size=(320, 240))
    params = {"sequence": "sample", "image_root": str(root), "pairs": str(root / "pairs.txt"), "methods": ["orb-nn"]}
    params |= {"profile": "repository", "output_dir": str(tmp_path / "out"), "cache_dir": str(tmp_path / "cache")}
    params |= {"device": "cpu", **changes}
    path = tmp_path / "sample.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


@pytest.mark.reliability
def test_a_sample_run_exported_as_the_authors_npy_and_imported_back_gives_the_same_ap_and_mr(
    tmp_path, capsys, notebooks_here
):
    params = sample_params(tmp_path)
    out = tmp_path / "out"
    assert run_cli(capsys, "run", str(params))[0] == 0
    code, said, err = run_cli(capsys, "results", str(out), "--export", "npy")
    assert code == 0, err
    exported = out / "exports" / f"sample_orb-nn_{shown_run(out, 'orb-nn')}.npy"
    assert f"orb-nn: {exported} (AP " in said
    shared = np.load(exported, allow_pickle=True).item()  # as the authors' code reads it
    ran = scoring.load_pairs_table(out, "orb-nn")
    assert shared["qImages"] == ran["query"].tolist() and shared["gt"] == ran["label"].tolist()
    assert shared["inliers"].tolist() == ran["num_inliers"].tolist()
    assert shared["average_precision"] == average_precision_score(ran["label"], ran["score"])

    # Back into the run's own folder (beside orb-nn) and into a folder of its own.
    for folder in (out, tmp_path / "back"):
        code, _, err = import_scores(capsys, exported, "orb-nn-back", folder, "sample")
        assert code == 0, err
        back, original = results_row(capsys, folder, "orb-nn-back"), results_row(capsys, out, "orb-nn")
        assert (back["ap"], back["max_recall"]) == (original["ap"], original["max_recall"])
        assert 0 < original["max_recall"] < 1
    assert runs.resolved_params(out) is not None  # the computed run's other files stay beside the import

    # A later run of the folder keeps the imported method, and a folder of other labels refuses it.
    assert run_cli(capsys, "run", str(params))[0] == 0
    assert results_row(capsys, out, "orb-nn-back")["ap"] == original["ap"]
    flipped = authors_npy(tmp_path / "other.npy")
    before = snapshot(out)
    code, _, err = import_scores(capsys, flipped, "other", out, "sample")
    assert code == 2 and "scored on other pairs or labels" in one_sentence(err)
    assert snapshot(out) == before


# ------------------------------------------- imported pairs on real Gardens Point --
# Eight real pairs: night_right frames against day_right ones (the same frame true, far ones false).
GP8 = [
    ("night_right/Image005.jpg", "day_right/Image005.jpg", 1),
    ("night_right/Image005.jpg", "day_right/Image060.jpg", 0),
    ("night_right/Image020.jpg", "day_right/Image021.jpg", 1),
    ("night_right/Image020.jpg", "day_right/Image090.jpg", 0),
    ("night_right/Image040.jpg", "day_right/Image040.jpg", 1),
    ("night_right/Image040.jpg", "day_right/Image120.jpg", 0),
    ("night_right/Image100.jpg", "day_right/Image101.jpg", 1),
    ("night_right/Image100.jpg", "day_right/Image150.jpg", 0),
]
GP8_SCORES = [0.9, 0.95, 0.8, 0.1, 0.7, 0.2, 0.6, 0.3]  # one false pair above every true one


def scores_csv(path: Path, rows) -> Path:
    path.write_text("query,reference,label,score\n" + "".join(f"{q},{r},{lab},{s}\n" for q, r, lab, s in rows))
    return path


def gp8_params(tmp_path: Path, root: Path, **changes) -> Path:
    pairs = tmp_path / "gp8.txt"
    pairs.write_text("".join(f"{q} {r} {lab}\n" for q, r, lab in GP8))
    params = {"sequence": "gp8", "image_root": str(root), "pairs": str(pairs), "methods": ["orb-nn"], "device": "cpu"}
    params |= {"profile": "repository", "output_dir": str(tmp_path / "out"), "cache_dir": str(tmp_path / "cache")}
    path = tmp_path / "gp8.yaml"
    path.write_text(yaml.safe_dump(params | changes))
    return path


def rows_with(*changes: tuple[int, tuple]) -> list[tuple]:
    rows = [(*pair, score) for pair, score in zip(GP8, GP8_SCORES)]
    for index, row in changes:
        rows[index] = row
    return rows


@pytest.mark.reliability
@pytest.mark.real_data
@pytest.mark.parametrize(
    ("rows", "line", "words"),
    [
        # Pair 1 listed twice (a pair file's line 3), pair 2 missing: AP 1.0 instead of 0.95's ranking.
        (rows_with((2, (*GP8[1], 0.95))), 4, "duplicate pair night_right/Image005.jpg day_right/Image060.jpg"),
        (rows_with((2, ("night_right/./Image005.jpg", "day_right/Image005.jpg", 1, 0.8))), 4, "duplicate pair"),
        (rows_with((2, ("night_right/Image020.jpg", "night_right/Image020.jpg", 1, 0.8))), 4, "self-pair"),
        (rows_with((2, ("day_right/Image005.jpg", "night_right/Image005.jpg", 1, 0.8))), 4, "in the other order"),
        (rows_with((5, ("night_right/Image040.jpg", "day_right/Image120.jpg", 2, 0.2))), 7, "label must be 0 or 1"),
        (rows_with((5, ("/abs/Image040.jpg", "day_right/Image120.jpg", 0, 0.2))), 7, "absolute path"),
        # Gardens Point's night_right frames 179 and 183 are byte-identical: a self-pair by content.
        (rows_with((5, ("night_right/Image179.jpg", "night_right/Image183.jpg", 0, 0.2))), 7, "self-pair by content"),
    ],
    ids=[
        "duplicate-and-missing",
        "duplicate-spelled-with-dot",
        "self-pair",
        "reversed",
        "label",
        "absolute",
        "content",
    ],
)
def test_imported_scores_obey_every_rule_of_a_pair_file(shared_data, tmp_path, capsys, rows, line, words):
    source = scores_csv(tmp_path / "scores.csv", rows)
    out = tmp_path / "out"
    argv = ["import-scores", str(source), "--sequence", "gp8", "--method", "ext", "--output-dir", str(out)]
    if words == "self-pair by content":  # the one rule that reads the images
        argv += ["--image-root", str(shared_data / "gardens_point")]
    code, _, err = run_cli(capsys, *argv)
    assert code == 2 and f"{source}:{line}: " in one_sentence(err) and words in err, err
    assert not out.exists()


@pytest.mark.reliability
@pytest.mark.parametrize("bad", [float("inf"), -float("inf"), float("nan")])
def test_a_score_that_is_not_finite_is_refused_naming_its_row(tmp_path, capsys, bad):
    table = scores_csv(tmp_path / "scores.csv", rows_with((3, (*GP8[3], bad))))
    counts = np.array(INLIERS, dtype=float)
    counts[2] = bad
    npy = authors_npy(tmp_path / "scores.npy", "counts", inliers=counts)
    for source, where in ((table, f"{table}:5: "), (npy, f"{npy}: pair 2: ")):
        code, _, err = import_scores(capsys, source, "ext", tmp_path / "out")
        assert code == 2 and where in one_sentence(err), err
    assert not (tmp_path / "out").exists()


@pytest.mark.reliability
def test_a_score_file_format_is_read_from_its_content_not_its_name(tmp_path, capsys):
    shouted = authors_npy(tmp_path / "SCORES.NPY")
    code, _, err = import_scores(capsys, shouted, "sp-sg", tmp_path / "out")
    assert code == 0, err
    assert scoring.load_pairs_table(tmp_path / "out", "sp-sg")["num_inliers"].tolist() == INLIERS
    table = scores_csv(tmp_path / "table.npy", rows_with())  # a table, whatever its name says
    code, _, err = import_scores(capsys, table, "from-table", tmp_path / "table")
    assert code == 0, err
    marker = tmp_path / "ran"
    evil = authors_npy(tmp_path / "EVIL.Npy", gt=[RunsCode(marker)] * 6)
    code, _, err = import_scores(capsys, evil, "x", tmp_path / "evil")
    assert code == 2 and "refused without running it" in one_sentence(err)
    assert not marker.exists() and not (tmp_path / "evil").exists()


@pytest.fixture
def gp8_run(shared_data, tmp_path, capsys, notebooks_here) -> Path:
    """The params of gp8 with orb-nn run into tmp_path/out."""
    params = gp8_params(tmp_path, shared_data / "gardens_point")
    code, _, err = run_cli(capsys, "run", str(params))
    assert code == 0, err
    return params


@pytest.mark.reliability
@pytest.mark.real_data
def test_an_import_never_joins_another_sequence(gp8_run, tmp_path, capsys):
    out = tmp_path / "out"
    source = scores_csv(tmp_path / "scores.csv", rows_with())
    before = snapshot(out)
    code, _, err = import_scores(capsys, source, "ext", out, "other_place")
    assert code == 2 and "holds sequence 'gp8', not 'other_place'" in one_sentence(err)
    flipped = scores_csv(tmp_path / "flipped.csv", rows_with((1, (*GP8[1][:2], 1, GP8_SCORES[1]))))
    code, _, err = import_scores(capsys, flipped, "ext", out, "gp8")
    assert code == 2 and "scored on other pairs or labels" in one_sentence(err)
    assert snapshot(out) == before


@pytest.fixture
def computed_run(tmp_path, capsys, request) -> Path:
    """orb-nn computed into tmp_path/out: on eight real Gardens Point pairs when $GVBENCH_DATA names
    the data folder, else on eight pairs of the sample render."""
    request.getfixturevalue("notebooks_here")
    if os.environ.get("GVBENCH_DATA"):
        params = gp8_params(tmp_path, request.getfixturevalue("shared_data") / "gardens_point")
    else:
        params = sample_params(tmp_path, limit=8)
    code, _, err = run_cli(capsys, "run", str(params))
    assert code == 0, err
    return tmp_path / "out"


@pytest.mark.reliability
def test_an_import_under_a_computed_methods_name_adds_a_run_and_says_which_the_folder_shows(
    computed_run, tmp_path, capsys
):
    out = computed_run
    computed_id, computed = shown_run(out, "orb-nn"), scoring.evaluate(out, write=False).set_index("method")
    table = scoring.load_pairs_table(out, "orb-nn")
    first_false = int(np.flatnonzero(table["label"].to_numpy() == 0)[0])
    scores = table["label"].to_numpy(dtype=float) + 0.01 * np.arange(len(table))
    scores[first_false] = 2.0  # one false pair above every true one
    source = scores_csv(tmp_path / "scores.csv", zip(table["query"], table["reference"], table["label"], scores))
    imported_ap = evaluate_scores(table["label"].to_numpy(), scores)["ap"]
    assert imported_ap != computed.loc["orb-nn", "ap"]  # what follows tells the two runs apart
    before = hashes(out / runs.RUNS)

    sequence = method_outputs.read_run_json(out, "orb-nn")["sequence"]
    code, said, err = import_scores(capsys, source, "orb-nn", out, sequence)
    assert code == 0, err
    after = hashes(out / runs.RUNS)
    assert {name: after.get(name) for name in before} == before  # no byte of the computed run changed
    (imported_id,) = set(run_ids(out)) - {computed_id}
    assert shown_run(out, "orb-nn") == imported_id
    command = f"python -m gvbench_nb results {out} --run {computed_id}"
    lines = [line for line in said.splitlines() if "now shows" in line]
    assert len(lines) == 1 and imported_id in lines[0] and lines[0].endswith(command), said
    assert scoring.evaluate(out, write=False).set_index("method").loc["orb-nn", "ap"] == pytest.approx(imported_ap)

    code, shown, err = run_cli(capsys, "results", str(out), "--run", computed_id)
    assert code == 0, err
    row = next(line.split() for line in shown.splitlines() if line.split()[:1] == ["orb-nn"])
    assert f"{computed.loc['orb-nn', 'ap']:.3f}" in row and f"{imported_ap:.3f}" not in row, shown


def exported_ap(path: Path) -> float:
    return float(np.load(path, allow_pickle=True).item()["average_precision"])


def run_ap(capsys, out: Path, run_id: str) -> float:
    """The AP ``results OUT --run ID`` shows for orb-nn (read from the run it names)."""
    code, _, err = run_cli(capsys, "results", str(out), "--run", run_id)
    assert code == 0, err
    return float(scoring.evaluate(runs.find_run(out, run_id), write=False).set_index("method").loc["orb-nn", "ap"])


@pytest.mark.reliability
@pytest.mark.real_data
def test_an_export_names_its_run_and_states_that_runs_ap(gp8_run, tmp_path, capsys):
    out = tmp_path / "out"
    code, said, err = run_cli(capsys, "results", str(out), "--export", "npy")
    assert code == 0, err
    first_id = shown_run(out, "orb-nn")
    first = out / "exports" / f"gp8_orb-nn_{first_id}.npy"
    first_ap = run_ap(capsys, out, first_id)
    assert f"orb-nn: {first} (AP {first_ap:.4f})" in said and exported_ap(first) == pytest.approx(first_ap)
    first_bytes = first.read_bytes()

    # A rerun under another profile: the earlier export still names its run and states that run's AP ...
    assert run_cli(capsys, "run", str(gp8_run), "--profile", "paper")[0] == 0
    second_id = shown_run(out, "orb-nn")
    assert second_id != first_id and first.read_bytes() == first_bytes
    assert exported_ap(first) == pytest.approx(run_ap(capsys, out, first_id))
    # ... and a second export names the new run and states its AP.
    code, said, err = run_cli(capsys, "results", str(out), "--export", "npy")
    assert code == 0, err
    second = out / "exports" / f"gp8_orb-nn_{second_id}.npy"
    second_ap = run_ap(capsys, out, second_id)
    # The folder shows orb-nn under both profiles, a row each: each row's export names its run.
    assert f"orb-nn (paper profile): {second} (AP {second_ap:.4f})" in said
    assert f"orb-nn (repository profile): {first} (AP {first_ap:.4f})" in said
    assert exported_ap(second) == pytest.approx(second_ap) and first.read_bytes() == first_bytes
    assert sorted(p.name for p in tmp_path.rglob("*.npy")) == sorted([first.name, second.name])
    assert sorted((out / "exports").iterdir()) == sorted([first, second])


@pytest.mark.reliability
@pytest.mark.real_data
def test_a_name_that_is_not_a_plain_file_name_is_refused_before_any_folder(shared_data, tmp_path, capsys):
    work = tmp_path / "a" / "b" / "c" / "d"
    work.mkdir(parents=True)
    keep = tmp_path / "keep_ext.npy"
    keep.write_bytes(b"the user's own")
    source = scores_csv(tmp_path / "scores.csv", rows_with())
    out = work / "out"
    params = gp8_params(work, shared_data / "gardens_point", sequence="../../../../keep")
    code, _, err = run_cli(capsys, "run", str(params))
    assert code == 2 and f"{params}: sequence '../../../../keep'" in one_sentence(err)
    for option, name in (("--sequence", "../../../../keep"), ("--method", ".."), ("--method", "a/b")):
        names = {"--sequence": "gp8", "--method": "ext"} | {option: name}
        argv = ["import-scores", str(source), "--sequence", names["--sequence"], "--method", names["--method"]]
        code, _, err = run_cli(capsys, *argv, "--output-dir", str(out))
        assert code == 2 and f"{option} {name!r}" in one_sentence(err), err
    assert not out.exists() and not (work / "cache").exists() and keep.read_bytes() == b"the user's own"
