"""Published reference values shipped in ``gvbench_nb/reference_values/``, never labelled as ours:
``paper_table.csv`` (the paper's, %, hloc chain: our ``paper`` profile), ``gvbench_repo_table.csv``
(the GV-Bench README's, fractions: our ``repository`` profile) and ``paper_sequences.csv`` (the
paper's text's sequence summary and conditions; blank where not stated). Loaders return fractions."""

from __future__ import annotations

from importlib import resources

import pandas as pd

PAPER_LABEL = "paper"
REPOSITORY_LABEL = "GV-Bench repository"
METRICS = ("ap", "max_recall")
COLUMNS = ["reference_name", "method", "sequence", *METRICS]

# The repository's matcher names (image-matching-models) -> ours, where the method is the same:
# its 'xfeat' is XFeat sparse with mutual nearest neighbours (our xfeat-nn); 'superpoint-lg' is
# SuperPoint + LightGlue. master (MASt3R), roma, duster (DUSt3R) and sift-lg have no method here.
REPOSITORY_METHODS: dict[str, str] = {
    "sift-nn": "sift-nn",
    "disk-lg": "disk-lg",
    "superpoint-lg": "sp-lg",
    "xfeat": "xfeat-nn",
    "loftr": "loftr",
}


def _read(
    name: str, table: pd.DataFrame | None = None, columns: tuple[str, ...] = ("sequence", *METRICS)
) -> pd.DataFrame:
    table = _read_csv(name) if table is None else table
    if not set(columns) <= set(table.columns):
        raise ValueError(f"{name}: expected columns {sorted(columns)}, got {list(table.columns)}")
    return table


def paper_table(table: pd.DataFrame | None = None, where: str = "paper_table.csv") -> pd.DataFrame:
    """The paper's AP/MR as fractions, ``reference_name`` the paper's (e.g. SIFT+NN); ``table``: one in
    the shipped format (``method,sequence,ap,max_recall`` in %) read from ``where``, default the shipped one."""
    from gvbench_nb import methods as method_registry

    raw = _read(where, table, ("method", "sequence", *METRICS)).rename(columns={"method": "reference_name"})
    by_paper_name = {conf["paper_name"]: name for name, conf in method_registry.RECIPES["paper"].items()}
    raw["method"] = raw["reference_name"].map(by_paper_name)
    for metric in METRICS:
        raw[metric] = raw[metric] / 100.0
    return raw[COLUMNS]


def repository_table() -> pd.DataFrame:
    """The GV-Bench repository's AP/MR (already fractions). ``reference_name`` is its matcher name."""
    raw = _read("gvbench_repo_table.csv").rename(columns={"matcher": "reference_name"})
    raw["method"] = raw["reference_name"].map(REPOSITORY_METHODS)
    return raw[COLUMNS]


def paper_sequences() -> pd.DataFrame:
    """The paper's text values of its sequences (``paper_sequences.csv``); NaN where not stated."""
    return _read_csv("paper_sequences.csv")


def _read_csv(name: str) -> pd.DataFrame:
    path = resources.files("gvbench_nb").joinpath("reference_values").joinpath(name)
    with path.open("r", encoding="utf-8") as handle:
        return pd.read_csv(handle)
