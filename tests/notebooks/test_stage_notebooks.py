"""The notebooks, executed with papermill as `run` and `report` do, write the right values and agree
with results.csv; an analysis notebook whose results are missing names the command that makes them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers import PAIRS, check_stage_outputs, papermill_from, write_params, write_root

from gvbench_nb import notebook
from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.reporting import execute
from gvbench_nb.runner import config, method_outputs, runs, sequence_build

LIMIT = 24  # pairs of the sample; its first 24 hold true and false ones
METHOD = "sift-nn"


def errors_in(executed: Path) -> list[str]:
    """The error outputs an executed notebook holds."""
    cells = json.loads(executed.read_text())["cells"]
    return [f"{o['ename']}: {o['evalue']}" for c in cells for o in c.get("outputs", []) if o["output_type"] == "error"]


@pytest.fixture(scope="module")
def sample_params(tmp_path_factory) -> Path:
    """params/sample.yaml with sift-nn only and every path (render, pairs, outputs) in a temporary folder."""
    folder = tmp_path_factory.mktemp("sample")
    raw = yaml.safe_load((config.PROJECT_ROOT / "params" / "sample.yaml").read_text())
    raw.update(image_root="data", pairs="data/pairs.txt", output_dir="out", methods=[METHOD])
    path = folder / "sample.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def executed_notebooks(stage_run: Path) -> Path:
    """Where ``stage_run`` keeps the executed notebooks: beside the output folder, which is the package's."""
    return stage_run.parent / "executed"


@pytest.fixture(scope="module")
def stage_run(sample_params) -> Path:
    """01_sequence, 02_verify and 03_evaluate executed on LIMIT sample pairs; the output folder."""
    out, executed = sample_params.parent / "out", sample_params.parent / "executed"
    common = {"params_file": str(sample_params), "limit": LIMIT}
    execute.execute_notebook("01_sequence.ipynb", executed / "01_sequence.ipynb", common)
    execute.execute_notebook("02_verify.ipynb", executed / "02_verify.ipynb", {**common, "method": METHOD})
    execute.execute_notebook("03_evaluate.ipynb", executed / "03_evaluate.ipynb", {"params_file": str(sample_params)})
    return out


@pytest.mark.slow
def test_stage_notebooks_write_one_row_a_pair_and_the_metrics_those_rows_give(sample_params, stage_run):
    sequence = sequence_build.prepare_sequence(config.load_params(sample_params, limit=LIMIT))
    assert len(sequence.pairs) == LIMIT and 0 < sum(p.label for p in sequence.pairs) < LIMIT
    row = check_stage_outputs(stage_run, METHOD, sequence.pairs)
    assert row["sequence"] == "sample" and row["profile"] == "repository"
    for name in ("01_sequence.ipynb", "02_verify.ipynb", "03_evaluate.ipynb"):
        assert errors_in(executed_notebooks(stage_run) / name) == [], name
    # 02_verify's figure is in the run it added; the others, of no run, at the folder's top
    run = runs.method_folder(stage_run, METHOD).parent
    figures = (
        "sequence_positives_per_query.png",
        "sequence_examples.png",
        f"{run}/inliers_{METHOD}.png",
        "pr_curves.png",
    )
    for figure in figures:
        assert (stage_run / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", figure


@pytest.mark.slow
def test_analysis_notebooks_agree_with_the_results_they_read(stage_run, tmp_path):
    results = pd.read_csv(stage_run / "results.csv").set_index("method")
    read_only = {"output_dirs": [str(stage_run)], "params_files": [], "output_dir": str(tmp_path)}
    execute.execute_notebook(
        "analysis_uncertainty.ipynb", tmp_path / "uncertainty.ipynb", {**read_only, "n_resamples": 50}
    )
    intervals = pd.read_csv(tmp_path / "bootstrap_intervals.csv").set_index(["method", "metric"])
    for metric in ("ap", "max_recall"):
        low, estimate, high = intervals.loc[(METHOD, metric), ["low", "estimate", "high"]]
        assert estimate == pytest.approx(results.loc[METHOD, metric], rel=1e-5)
        assert 0 <= low <= high <= 1
    execute.execute_notebook("analysis_results_table.ipynb", tmp_path / "results_table.ipynb", read_only)
    joined = pd.read_csv(tmp_path / "results_with_paper.csv")
    ours = joined[joined["source"] == "ours"].set_index("method")
    assert list(ours.index) == [METHOD]
    assert np.allclose(ours.loc[[METHOD], ["ap", "max_recall"]], results.loc[[METHOD], ["ap", "max_recall"]], rtol=1e-5)
    assert (tmp_path / "max_recall_radar.png").is_file()
    # The diagonal of the transfer matrix is MR itself; Table III of the synthetic route holds its
    # values and no Average.
    execute.execute_notebook("analysis_deployment.ipynb", tmp_path / "deployment.ipynb", read_only)
    transfer = pd.read_csv(tmp_path / "transfer.csv").set_index("method")
    assert transfer.loc[METHOD, "recall"] == pytest.approx(results.loc[METHOD, "max_recall"], rel=1e-9)
    assert transfer.loc[METHOD, "false_loops"] == 0
    execute.execute_notebook("analysis_paper.ipynb", tmp_path / "paper.ipynb", read_only)
    table_iii = pd.read_csv(tmp_path / "table_iii_synthetic.csv", header=[0, 1], index_col=[0, 1])
    assert table_iii.columns.get_level_values(0).unique().tolist() == ["sample"]
    assert table_iii[("sample", "ap")].iloc[0] == pytest.approx(results.loc[METHOD, "ap"], rel=1e-9)


@pytest.mark.slow
@pytest.mark.reliability
def test_an_analysis_notebook_with_results_missing_names_the_command_and_runs_nothing(sample_params, tmp_path):
    empty = tmp_path / "empty"
    raw = yaml.safe_load(sample_params.read_text())
    data = sample_params.parent / "data"
    raw.update(image_root=str(data), pairs=str(data / "pairs.txt"), output_dir=str(empty))
    params = tmp_path / "empty.yaml"
    params.write_text(yaml.safe_dump(raw))
    with pytest.raises(execute.NotebookFailedError) as failure:
        execute.execute_notebook(
            "analysis_inlier_histograms.ipynb",
            tmp_path / "histograms.ipynb",
            {"output_dirs": [str(empty)], "params_files": [str(params)], "output_dir": str(tmp_path / "figures")},
        )
    assert failure.value.ename == "ResultsMissingError"
    assert f"python -m gvbench_nb run {params} --methods {METHOD}" in failure.value.evalue
    assert not (empty / METHOD).exists()


# ------------------------------------------------ a notebook's parameters --
@pytest.mark.reliability
@pytest.mark.parametrize(
    "value, expected",
    [
        (
            '["../outputs/gardens_point"]',
            """must be a list, got '["../outputs/gardens_point"]': papermill's -p passes text, \
give a list with -y, e.g. -y 'output_dirs: ["../outputs/gardens_point"]'""",
        ),
        ("../outputs/gardens_point", "-y 'output_dirs: [../outputs/gardens_point]'"),
        (3, "must be a list, got 3"),
    ],
)
def test_a_notebook_parameter_of_the_wrong_type_is_one_sentence_naming_it_and_the_y_form(value, expected):
    # typing.Optional, as the notebooks write it
    declared = {"output_dirs": list, "limit": Optional[int], "methods": str | list | None, "k": float}  # noqa: UP045
    namespace = {"__annotations__": declared, "output_dirs": ["a"], "limit": None, "methods": "sift-nn", "k": 3}
    notebook.check_parameters(namespace)  # every value of its type (an int is a number)
    with pytest.raises(notebook.ParameterError) as error:
        notebook.check_parameters({**namespace, "output_dirs": value})
    assert str(error.value).startswith("notebook parameter output_dirs must be a list, got")
    assert expected in str(error.value) and "\n" not in str(error.value)


@pytest.mark.reliability
def test_an_analysis_notebook_given_a_list_as_text_names_the_parameter_and_the_y_form(tmp_path):
    with pytest.raises(execute.NotebookFailedError) as failure:  # as `papermill ... -p output_dirs '[...]'`
        execute.execute_notebook(
            "analysis_inlier_histograms.ipynb",
            tmp_path / "histograms.ipynb",
            {"output_dirs": '["../outputs/gardens_point"]', "output_dir": str(tmp_path / "figures")},
        )
    assert failure.value.ename == "ParameterError"
    assert "output_dirs must be a list" in failure.value.evalue
    assert """-y 'output_dirs: ["../outputs/gardens_point"]'""" in failure.value.evalue
    assert not (tmp_path / "figures").exists()


def study(folder: Path, relative: bool) -> Path:
    """A complete params file of sequence 'pmf' kept in ``folder`` (outside params/): orb-nn on four photographs."""
    write_root(folder / "images")
    write_pairs(folder / "pairs.txt", PAIRS)
    if not relative:
        return write_params(folder, sequence="pmf", methods=["orb-nn"])
    names = ("pairs.txt", "images", "out", "cache")
    return write_params(folder, sequence="pmf", methods=["orb-nn"], **dict(zip(config.PATH_KEYS, names)))


@pytest.mark.reliability
def test_every_params_key_given_without_a_params_file_are_the_params_relative_to_the_working_folder(
    tmp_path, monkeypatch, capsys
):
    keys = config.read_yaml_mapping(study(tmp_path / "study", relative=True))
    monkeypatch.chdir(tmp_path / "study")
    params = notebook.load_params(None, **keys)
    assert params["pairs"] == str(tmp_path / "study" / "pairs.txt")
    assert params["output_dir"] == str(tmp_path / "study" / "out") and params["methods"] == ["orb-nn"]
    said = capsys.readouterr().out
    assert f"relative paths are read from {tmp_path / 'study'}" in said
    with pytest.raises(config.ParamsError) as error:
        notebook.load_params(None, **{k: v for k, v in keys.items() if k != "profile"})
    assert str(error.value).startswith("the notebook's parameters lack profile, and no params file in")
    assert "give every key (-f PARAMS.yaml), or the params file of these parameters (-p params_file PATH)" in str(
        error.value
    )


@pytest.mark.slow
@pytest.mark.reliability
def test_a_stage_notebook_given_every_params_key_runs_on_them_from_any_folder(tmp_path):
    absolute = study(tmp_path / "kept" / "anywhere", relative=False)
    said = papermill_from(
        config.PROJECT_ROOT, "02_verify", tmp_path / "a.ipynb", "-f", str(absolute), "-p", "method", "orb-nn"
    )
    assert f"relative paths are read from {config.PROJECT_ROOT}" in said
    assert (method_outputs.method_dir(tmp_path / "kept" / "anywhere" / "out", "orb-nn") / "pairs.csv").is_file()
    relative, elsewhere = study(tmp_path / "study", relative=True), tmp_path / "study"
    for stage in ("01_sequence", "02_verify", "03_evaluate"):
        method = ["-p", "method", "orb-nn"] if stage == "02_verify" else []  # the others take no method
        said = papermill_from(elsewhere, stage, tmp_path / f"{stage}.ipynb", "-f", str(relative), *method)
        assert f"relative paths are read from {elsewhere}" in said
    row = check_stage_outputs(elsewhere / "out", "orb-nn", PAIRS)
    assert row["sequence"] == "pmf"
