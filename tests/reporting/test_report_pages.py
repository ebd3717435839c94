"""The report's study pages appear exactly where their inputs exist, with the inputs' parameters."""

from __future__ import annotations

import json

import pandas as pd
from written_runs import add_run

from gvbench_nb.reporting import report


def test_study_pages_where_their_inputs_exist(tmp_path):
    outputs = tmp_path / "outputs"
    table = pd.DataFrame({"pair_index": [0, 1], "query": ["q", "q"], "reference": ["r0", "r1"], "label": [1, 0]})
    built = {"params.resolved.yaml": "pairs_builder: retrieval\nbuilder_options: {descriptor: bow}\n"}
    for name in ("compared", "plain", "built"):
        add_run(
            outputs / name,
            "sift-nn",
            table.assign(score=[2, 1]),
            {"sequence": name},
            files=built if name == "built" else None,
        )
        pd.DataFrame({"sequence": [name], "method": ["sift-nn"]}).to_csv(outputs / name / "results.csv", index=False)
    (outputs / "compared" / "verifiers").mkdir()
    (outputs / "compared" / "verifiers" / "verifiers.csv").write_text("verifier\n")
    sweep = outputs / "sweep_a"
    (sweep / "images").mkdir(parents=True)
    (sweep / "images" / "route.json").write_text(json.dumps({"n_frames": 8, "image_size": [160, 120], "seed": 3}))
    rows = [("illumination", 0.0, "orb-nn", "repository"), ("illumination", 1.0, "orb-nn", "repository")]
    pd.DataFrame(rows, columns=["condition", "strength", "method", "profile"]).to_csv(sweep / "sweep.csv")
    (outputs / "unfinished" / "images").mkdir(parents=True)  # a route without sweep.csv: no page
    (outputs / "unfinished" / "images" / "route.json").write_text("{}")

    folders = [outputs / name for name in ("compared", "plain", "built")]
    jobs = {(name, sequence): parameters for name, _, parameters, sequence in report.study_jobs(tmp_path, folders)}
    assert set(jobs) == {
        ("analysis_verifiers.ipynb", "compared"),
        ("analysis_doppelgangers.ipynb", "compared"),
        ("00_build_sequence.ipynb", "built"),
        ("analysis_condition_sweep.ipynb", "sweep sweep_a"),
    }
    assert jobs[("analysis_verifiers.ipynb", "compared")]["output_dir"] == str(outputs / "compared" / "verifiers")
    assert jobs[("00_build_sequence.ipynb", "built")]["compare_descriptors"] == ["bow"]
    swept = jobs[("analysis_condition_sweep.ipynb", "sweep sweep_a")]
    assert (swept["methods"], swept["strengths"], swept["n_frames"], swept["seed"]) == (["orb-nn"], [0.0, 1.0], 8, 3)
    assert swept["profile"] == {"orb-nn": "repository"} and swept["output_dir"] == str(sweep)
