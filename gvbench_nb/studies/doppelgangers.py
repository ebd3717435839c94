"""What notebooks/analysis_doppelgangers.ipynb computes: the Doppelgangers classifier beside GV."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb import methods as method_registry
from gvbench_nb.evaluation import run_tables
from gvbench_nb.io_utils import atomic_write_json
from gvbench_nb.studies import verifier_inputs


def in_domain_weights_path(
    folder: str | os.PathLike[str],
    cached: verifier_inputs.CachedMatches,
    conf: dict[str, Any],
    split_conf: dict[str, Any],
) -> Path:
    """Where in-domain weights live; the name says what they are (sequence, matches, split,
    size, epochs, seed) and ends in the hash of everything that made them."""
    identity = {
        "verifier": conf,
        "split": split_conf,
        "matches": {
            "method": cached.method,
            "conf_hash": method_registry.conf_hash(cached.conf),
            "sequence": cached.sequence,
        },
    }
    name = (
        f"doppelgangers_in-domain_{cached.sequence}_{cached.method}-{cached.conf['profile']}_train-split"
        f"_size{conf['size']}_ep{conf['epochs']}_seed{conf['seed']}_{method_registry.conf_hash(identity)}.pt"
    )
    return Path(folder) / name


def train_in_domain(
    cached: verifier_inputs.CachedMatches,
    train_pairs: pd.DataFrame,
    conf: dict[str, Any],
    path: Path,
    progress: bool = True,
) -> dict[str, Any]:
    """Train the Doppelgangers architecture on ``train_pairs`` (published recipe: focal loss, Adam)
    and save ``{'dec': state_dict, 'info': ...}`` at ``path`` (loadable by ``load_doppelgangers``).
    Returns the info: pairs used, seconds to build inputs and to train, the history."""
    import torch  # here only: reading cached matches and scoring them need no torch

    from gvbench_nb.verification.doppelgangers import DoppelgangersClassifier, train_classifier

    chosen = verifier_inputs.balanced_subset(train_pairs["label"].to_numpy(), conf["max_train_pairs"], conf["seed"])
    subset = train_pairs.iloc[chosen]
    start = time.perf_counter()
    inputs = verifier_inputs.doppelgangers_inputs(cached, subset, conf["size"], progress)
    input_seconds = time.perf_counter() - start
    torch.manual_seed(conf["seed"])  # the initialisation; train_classifier seeds the batch order
    model = DoppelgangersClassifier()
    start = time.perf_counter()
    labels = np.array(subset["label"], dtype=np.int64)  # a writable copy (torch refuses read-only arrays)
    training = {key: conf[key] for key in ("epochs", "lr", "batch_size", "seed")}
    history = train_classifier(model, inputs, labels, progress=progress, **training)
    train_seconds = time.perf_counter() - start
    info = {
        "weights": path.name,
        "matches": cached.label,
        "conf": conf,
        "n_train_pairs": int(len(subset)),
        "n_train_positives": int(subset["label"].sum()),
        "input_seconds": input_seconds,
        "train_seconds": train_seconds,
        "torch_threads": torch.get_num_threads(),
        "history": history,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"dec": model.state_dict(), "info": info}, path)
    atomic_write_json(path.with_suffix(".json"), info)
    return info


# ------------------------------------------------------- paper comparison --
PAPER_ROWS = {"SIFT+NN": "GV: SIFT+NN, F-RANSAC inliers", "Doppelgangers": "Doppelgangers"}


def doppelgangers_comparison(
    results: pd.DataFrame,
    paper: pd.DataFrame,
    sequence: str,
    verifiers_shown: SequenceType[str] = (verifier_inputs.PAPER_VERIFIER, "doppelgangers", "doppelgangers-in-domain"),
) -> pd.DataFrame:
    """GV vs Doppelgangers as the paper's supplementary table: ours on ``sequence``'s test split
    (source 'ours', with CIs and the weights used) beside the paper's SIFT+NN and Doppelgangers
    rows on its own sequences (source 'paper', as published). AP and MR as fractions."""
    ours = results[results["verifier"].isin(verifiers_shown)].copy()
    ours = ours.assign(source=run_tables.OURS_LABEL, sequence=f"{sequence} (test split)")
    theirs = paper[paper["paper_name"].isin(list(PAPER_ROWS))].copy()
    theirs = theirs.assign(
        source=run_tables.PAPER_LABEL, verifier=theirs["paper_name"].map(PAPER_ROWS), weights="", status="published"
    )
    columns = ["source", "sequence", "verifier", "ap", "max_recall", "ap_ci_low", "ap_ci_high", "max_recall_ci_low"]
    columns += ["max_recall_ci_high", "status", "weights"]
    return pd.concat([ours.reindex(columns=columns), theirs.reindex(columns=columns)], ignore_index=True)
