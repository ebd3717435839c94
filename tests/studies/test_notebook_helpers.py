"""What the notebooks load before they plot (``gvbench_nb.notebook``): reading never runs
the pipeline unless the notebook asks, and a gap names the command that fills it."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
from test_analysis import write_fake_run

from gvbench_nb import notebook
from gvbench_nb.runner import method_runs, scoring, sequence_build
from gvbench_nb.studies import alternative_verifiers


@pytest.fixture
def toy(tmp_path: Path, monkeypatch) -> tuple[Path, Path]:
    """(params file, its output folder) of a toy sequence; running a method is an error."""
    output_dir = tmp_path / "toy"
    (tmp_path / "pairs.txt").write_text("q0 r0 1\n")
    params = tmp_path / "toy.yaml"
    params.write_text(
        "sequence: toy\npairs: pairs.txt\nimage_root: .\nmethods: [sift-nn]\nprofile: repository\n"
        f"output_dir: {output_dir}\n"
    )

    def refuse(*args, **kwargs):
        raise AssertionError("the pipeline ran although the notebook did not ask")

    monkeypatch.setattr(method_runs, "run_method", refuse)
    return params, output_dir


@pytest.mark.reliability
def test_missing_results_raise_one_sentence_naming_the_command_and_run_nothing(toy):
    params, output_dir = toy
    with pytest.raises(notebook.ResultsMissingError) as error:
        notebook.load_results([output_dir], output_dir / "analysis", [params], ["sift-nn"])
    message = str(error.value)
    assert message.count(". ") == 0 and message.endswith(".") and "\n" not in message
    command = message.split("`")[1]
    assert shlex.split(command) == ["python", "-m", "gvbench_nb", "run", str(params.resolve()), "--methods", "sift-nn"]
    assert "compute_missing=True" in message and not (output_dir / "sift-nn").exists()


def test_compute_missing_runs_only_what_is_missing(toy, monkeypatch):
    params, output_dir = toy
    ran = []

    def fake_run(params, sequence, method, **options):
        ran.append([method])
        write_fake_run(output_dir)

    monkeypatch.setattr(method_runs, "run_method_of_params", fake_run)
    monkeypatch.setattr(sequence_build, "prepare_sequence", lambda params: "the sequence")
    inputs = notebook.load_results(
        str(output_dir), output_dir / "analysis", str(params), ["sift-nn"], compute_missing=True
    )
    assert ran == [["sift-nn"]]
    assert inputs.output_dirs == [str(output_dir)] and inputs.figures.is_dir()
    assert inputs.results["method"].tolist() == ["sift-nn"]
    assert notebook.sequence_of(inputs.results, output_dir) == "toy"
    # Everything present now: the same call runs nothing.
    notebook.load_results(str(output_dir), output_dir / "analysis", str(params), ["sift-nn"], compute_missing=True)
    assert ran == [["sift-nn"]]


def test_a_results_table_behind_its_runs_is_neither_read_nor_rewritten(toy):
    """results.csv is written for people: a notebook's table is the runs', whatever that file says."""
    params, output_dir = toy
    write_fake_run(output_dir)
    write_fake_run(output_dir, method="orb-nn")
    scoring.evaluate(output_dir, ["sift-nn"])  # results.csv lacks orb-nn
    before = (output_dir / "results.csv").read_text()
    assert notebook.require_results(params, ["sift-nn", "orb-nn"]) == output_dir
    inputs = notebook.load_results(str(output_dir), output_dir / "analysis", str(params), ["sift-nn", "orb-nn"])
    assert set(inputs.results["method"]) == {"sift-nn", "orb-nn"}
    assert (output_dir / "results.csv").read_text() == before


def test_no_params_files_reads_finished_runs_only(toy):
    params, output_dir = toy
    with pytest.raises(FileNotFoundError, match="does not exist; give the output_dir of a finished run"):
        notebook.load_results([output_dir], output_dir / "analysis", [], ["sift-nn"])
    write_fake_run(output_dir)
    scoring.evaluate(output_dir)
    assert len(notebook.load_results([output_dir], output_dir / "analysis", None).results) == 1
    with pytest.raises(notebook.ResultsMissingError, match="add it to output_dirs"):
        notebook.sequence_of(notebook.load_results([output_dir], output_dir / "analysis").results, "elsewhere")


def test_verifier_bench_names_the_run_with_its_output_folder_and_profile(toy, tmp_path, monkeypatch):
    params, _ = toy
    elsewhere = tmp_path / "elsewhere"
    with pytest.raises(notebook.ResultsMissingError) as error:
        notebook.open_verifier_bench(elsewhere, "sift-nn", tmp_path / "v", params_file=params, profile="paper")
    words = shlex.split(str(error.value).split("`")[1])
    assert words[words.index("--output-dir") + 1] == str(elsewhere) and words[words.index("--profile") + 1] == "paper"
    with pytest.raises(notebook.ResultsMissingError, match="run it on that sequence first"):
        notebook.open_verifier_bench(elsewhere, "sift-nn", tmp_path / "v")
    ran = []
    monkeypatch.setattr(sequence_build, "prepare_sequence", lambda params: params)
    monkeypatch.setattr(
        method_runs, "run_method_of_params", lambda params, sequence, method: ran.append((method, params["output_dir"]))
    )
    monkeypatch.setattr(alternative_verifiers, "open_bench", lambda *a, **k: ("bench", a, k))
    bench = notebook.open_verifier_bench(
        elsewhere,
        "sift-nn",
        tmp_path / "v",
        params_file=params,
        compute_missing=True,
        classifier={"epochs": 1},
        gap_frames=8,
    )
    assert ran == [("sift-nn", str(elsewhere))]
    assert bench[2] == {"overrides": {"doppelgangers-in-domain": {"epochs": 1}}, "gap_frames": 8}


def test_as_list_takes_one_path_or_many():
    assert notebook.as_list("../outputs/sample") == ["../outputs/sample"]
    assert notebook.as_list(Path("a")) == ["a"]
    assert notebook.as_list(["a", Path("b")]) == ["a", "b"]
    assert notebook.as_list(None) == [] and notebook.as_list([]) == []
