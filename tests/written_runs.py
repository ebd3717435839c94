"""Hand-made method results added to an output folder as a run, the way a door adds one
(``runs.new_run``: built aside, made visible by one rename), for the tests of what reads them."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.runner import runs, scoring


def add_run(
    output_dir: Path,
    method: str,
    table: pd.DataFrame,
    record: dict[str, Any] | None = None,
    view: bool = False,
    files: dict[str, str] | None = None,
) -> Path:
    """Add a run of ``method`` holding ``table`` (its pairs.csv) and ``record`` (its run.json, over a
    conf of the method under the repository profile); returns the method's folder in the run. The
    conf takes the registry's verifier unless ``record`` gives one, so hand-made methods of one
    folder share a recipe. ``view``: write the folder's results.csv too, as a door does; ``files``:
    other files of the run (name -> text), such as its params.resolved.yaml."""
    record = dict(record or {})
    conf = {"method": method, "paper_name": method, "profile": "repository"} | dict(record.pop("conf", {}))
    if "verifier" not in conf:
        with contextlib.suppress(GVBenchError, KeyError, ValueError):  # a method the registry does not know
            conf["verifier"] = method_registry.resolve_method(method, conf["profile"], None)["verifier"]
    with runs.new_run(output_dir, "run") as building:
        (building / method).mkdir()
        table.to_csv(building / method / "pairs.csv", index=False)
        body = {"sequence": "toy", "environment": {"device": "cpu"}} | record | {"conf": conf}
        (building / method / "run.json").write_text(json.dumps(body, default=str))
        for name, text in (files or {}).items():
            (building / name).write_text(text)
    if view:
        scoring.refresh_view(output_dir)
    return runs.finished_runs(output_dir)[-1][0] / method
