"""Alternative verifiers scoring a pair from a run's CACHED matches: ``gv-<model>-<estimator>-<score>``,
``sue``, ``doppelgangers[-in-domain]`` and ``learned_combination[+dg]``, each a conf in
``ALTERNATIVE_VERIFIERS``; learned ones never see a test place (``place_disjoint_split``)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb import methods as method_registry
from gvbench_nb.evaluation import bootstrap, run_tables
from gvbench_nb.io_utils import atomic_write_csv
from gvbench_nb.protocol import recipes, registry
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.protocol.ransac import ESTIMATORS
from gvbench_nb.protocol.weights import MissingWeightsError
from gvbench_nb.runner import scoring
from gvbench_nb.studies import doppelgangers, verifier_inputs

GV_SCORES = ("inliers", "inlier_ratio", "inliers_over_keypoints")


def gv_conf(model: str, estimator: str, score: str) -> dict[str, Any]:
    """The conf of one GV verifier; its thresholds are those of the paper profile's verifier."""
    if model not in verifier_inputs.MODEL_SHORT_NAMES or estimator not in ESTIMATORS or score not in GV_SCORES:
        raise KeyError(
            f"unknown GV verifier ({model}, {estimator}, {score}); models {list(verifier_inputs.MODEL_SHORT_NAMES)}, "
            f"estimators {list(ESTIMATORS)}, scores {list(GV_SCORES)}"
        )
    paper = recipes.profile_verifier("paper")
    thresholds = {key: paper[key] for key in ("threshold_px", "confidence", "max_iters")}
    return {"type": "gv", "model": model, "estimator": estimator, "score": score, **thresholds,
            "min_matches": verifier_inputs.MIN_MATCHES[model], "min_match_score": paper["min_match_score"]}  # fmt: skip


def gv_name(model: str, estimator: str, score: str) -> str:
    return f"gv-{verifier_inputs.MODEL_SHORT_NAMES[model]}-{verifier_inputs.ESTIMATOR_SHORT_NAMES[estimator]}-{score}"


ALTERNATIVE_VERIFIERS: dict[str, dict[str, Any]] = {
    gv_name(m, e, s): gv_conf(m, e, s) for m in verifier_inputs.MODEL_SHORT_NAMES for e in ESTIMATORS for s in GV_SCORES
}


DOPPELGANGERS_IN_DOMAIN = {"type": "doppelgangers", "weights": "in-domain", "size": 96, "epochs": 3,
                           "batch_size": 8, "lr": 5e-4, "max_train_pairs": 300, "seed": 0}  # fmt: skip
LEARNED_COMBINATION = {"type": "learned_combination", "base": verifier_inputs.PAPER_VERIFIER,
                       "features": list(verifier_inputs.FEATURES), "classifier": None, "C": 1.0}  # fmt: skip
ALTERNATIVE_VERIFIERS.update(
    {
        # slope 10 on distances in [0, 1] (1 - score / best score): a candidate with 10% fewer
        # inliers than the best weighs e^-1 of it. The paper's 350 was for NetVLAD distances.
        "sue": {"type": "sue", "base": verifier_inputs.PAPER_VERIFIER, "slope": 10.0, "top_k": 10},
        "doppelgangers": {"type": "doppelgangers", "weights": "official", "size": 1024},
        "doppelgangers-in-domain": DOPPELGANGERS_IN_DOMAIN,
        "learned_combination": LEARNED_COMBINATION,
        "learned_combination+dg": {**LEARNED_COMBINATION, "classifier": "doppelgangers-in-domain"},
    }
)


def resolve_verifier(name: str, **overrides: Any) -> dict[str, Any]:
    """A verifier's conf (a copy) with ``overrides`` applied; unknown names list the valid ones."""
    if name not in ALTERNATIVE_VERIFIERS:
        raise registry.UnknownNameError(registry.unknown_name_message("verifier", name, ALTERNATIVE_VERIFIERS))
    conf = json.loads(json.dumps(ALTERNATIVE_VERIFIERS[name]))
    unknown = [k for k in overrides if k not in conf]
    if unknown:
        raise KeyError(f"verifier {name!r} has no option(s) {unknown}; its options: {sorted(conf)}")
    conf.update(overrides)
    return conf


# --------------------------------------------------------------- evaluation --
@dataclass
class VerifierBench:
    """Scores verifiers on one run's cached matches (``pairs`` with a ``split`` column), fitting once.
    ``overrides`` maps a verifier to options replacing its conf (recorded in ``conf_hash``/``conf``)."""

    cached: verifier_inputs.CachedMatches
    pairs: pd.DataFrame
    split_conf: dict[str, Any]
    output_dir: Path
    progress: bool = True
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    weights_info: dict[str, dict[str, Any]] = field(default_factory=dict)  # verifier -> which weights scored it
    _gv: dict[str, pd.DataFrame] = field(default_factory=dict)
    _classifier: dict[str, pd.Series] = field(default_factory=dict)

    def conf(self, name: str) -> dict[str, Any]:
        """The verifier's registry conf with this bench's overrides."""
        return resolve_verifier(name, **self.overrides.get(name, {}))

    def used(self) -> pd.DataFrame:
        """Pairs of the train and test splits (dropped pairs are never scored)."""
        return self.pairs[self.pairs["split"] != verifier_inputs.SPLIT_DROPPED]

    def gv(self, conf: dict[str, Any]) -> pd.DataFrame:
        """GV features of every used pair under ``conf``'s model fit (computed once a fit conf)."""
        fit_conf = {k: v for k, v in conf.items() if k != "score"}
        key = method_registry.conf_hash(fit_conf)
        if key not in self._gv:
            self._gv[key] = verifier_inputs.gv_feature_table(self.cached, self.used(), fit_conf, self.progress)
        return self._gv[key]

    def classifier_probability(self, name: str, conf: dict[str, Any]) -> pd.Series:
        """P(same place) of a Doppelgangers verifier on every used pair."""
        if name in self._classifier:
            return self._classifier[name]
        from gvbench_nb.verification.doppelgangers import load_doppelgangers, predict

        if conf["weights"] == "official":
            model = load_doppelgangers()  # MissingWeightsError names the file and where to get it
            path = self.output_dir / f"doppelgangers_official_size{conf['size']}.pt"  # names the cached predictions
            self.weights_info[name] = {"weights": "official doppelgangers_classifier_loftr.pt"}
        else:
            path = doppelgangers.in_domain_weights_path(self.output_dir, self.cached, conf, self.split_conf)
            if path.is_file() and path.with_suffix(".json").is_file():
                info = json.loads(path.with_suffix(".json").read_text())
                info["reused"] = True
            else:
                info = doppelgangers.train_in_domain(
                    self.cached,
                    self.pairs[self.pairs["split"] == verifier_inputs.SPLIT_TRAIN],
                    conf,
                    path,
                    self.progress,
                )
                info["reused"] = False
            model = load_doppelgangers(path)
            self.weights_info[name] = info
        used = self.used()
        # Predictions are cached beside the weights, keyed by pair: inference costs minutes on a CPU.
        cache = path.with_name(path.stem + f".predictions-{self.cached.method}-{self.cached.conf['profile']}.csv")
        if cache.is_file():
            known = pd.read_csv(cache, keep_default_na=False).set_index(["query", "reference"])["probability"]
            wanted = pd.MultiIndex.from_arrays([used["query"], used["reference"]])
            if wanted.isin(known.index).all():
                self.weights_info[name]["predictions"] = f"reused {cache.name}"
                self._classifier[name] = pd.Series(known.loc[wanted].to_numpy(), index=used.index)
                return self._classifier[name]
        start = time.perf_counter()
        inputs = verifier_inputs.doppelgangers_inputs(self.cached, used, conf["size"], self.progress)
        probability = predict(model, inputs)
        self.weights_info[name]["predict_seconds"] = time.perf_counter() - start
        atomic_write_csv(cache, used[["query", "reference"]].assign(probability=probability))
        self._classifier[name] = pd.Series(probability, index=used.index)
        return self._classifier[name]

    def scores(self, name: str, conf: dict[str, Any] | None = None) -> pd.Series:
        """The verifier's score of every used pair (index of ``pairs``)."""
        conf = conf or self.conf(name)
        kind = conf["type"]
        if kind == "gv":
            return self.gv(conf)[conf["score"]]
        if kind == "sue":
            base = self.used()[["query", "reference"]].assign(score=self.scores(conf["base"]))
            return verifier_inputs.sue_pair_scores(base, conf["slope"], conf["top_k"])["score"]
        if kind == "doppelgangers":
            return self.classifier_probability(name, conf)
        if kind == "learned_combination":
            features = self.combination_features(conf)
            train = self.used()["split"] == verifier_inputs.SPLIT_TRAIN
            model = fit_combination(features[train], self.used().loc[train, "label"], conf)
            return pd.Series(model.predict_proba(features.to_numpy())[:, 1], index=features.index)
        raise KeyError(f"verifier {name!r} has unknown type {kind!r}")

    def combination_features(self, conf: dict[str, Any]) -> pd.DataFrame:
        features = self.gv(self.conf(conf["base"]))[list(conf["features"])].copy()
        if conf["classifier"]:
            features["classifier_probability"] = self.classifier_probability(
                conf["classifier"], self.conf(conf["classifier"])
            )
        return features

    def evaluate(
        self, names: Iterable[str], split: str = verifier_inputs.SPLIT_TEST, n_resamples: int = 1000, seed: int = 0
    ) -> tuple[pd.DataFrame, dict[str, pd.DataFrame], bootstrap.Bootstrap | None]:
        """AP, MR and query-bootstrap 95% CIs of each verifier on ``split`` (a verifier that cannot run: its
        reason in ``status``). Returns (rows, per-verifier score tables, bootstrap)."""
        rows, tables = [], {}
        part = self.used()[self.used()["split"] == split]
        for name in names:
            conf = self.conf(name)
            row = {"verifier": name, "conf_hash": method_registry.conf_hash(conf), "split": split,
                   "matches": self.cached.label, "n_pairs": len(part), "n_positives": int(part["label"].sum()),
                   "conf": json.dumps(conf, sort_keys=True)}  # fmt: skip
            try:
                start = time.perf_counter()
                score = self.scores(name, conf)
                row["seconds"] = time.perf_counter() - start
            except MissingWeightsError as error:
                rows.append({**row, "status": f"unavailable: {str(error).splitlines()[0]}"})
                continue
            tables[name] = part[["query", "reference", "label"]].assign(score=score.loc[part.index].to_numpy())
            metrics = evaluate_scores(
                tables[name]["label"].to_numpy(),
                tables[name]["score"].to_numpy(),
                where=f"verifier {name} on the {split} split of {self.cached.label}",
            )
            weights = self.weights_info.get(name) or self.weights_info.get(conf.get("classifier") or "")
            row.update(ap=metrics["ap"], max_recall=metrics["max_recall"], status="ok")
            rows.append({**row, "weights": weights["weights"] if weights else ""})
        results = pd.DataFrame(rows)
        boot = None
        if tables:
            boot = bootstrap.bootstrap(tables, n_resamples=n_resamples, seed=seed)
            wide = boot.intervals().pivot(index="method", columns="metric", values=["low", "high"])
            for metric in run_tables.METRICS:
                results[f"{metric}_ci_low"] = results["verifier"].map(wide[("low", metric)])
                results[f"{metric}_ci_high"] = results["verifier"].map(wide[("high", metric)])
        return results.reindex(columns=RESULT_COLUMNS), tables, boot


RESULT_COLUMNS = ["verifier", "split", "ap", "max_recall", "ap_ci_low", "ap_ci_high", "max_recall_ci_low"]
RESULT_COLUMNS += ["max_recall_ci_high", "n_pairs", "n_positives", "matches", "weights", "seconds", "status"]
RESULT_COLUMNS += ["conf_hash", "conf"]


def fit_combination(features: pd.DataFrame, labels: pd.Series, conf: dict[str, Any]) -> Any:
    """Standardised features -> ``LogisticRegression`` (lbfgs, deterministic), fitted on the given pairs."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    labels = np.asarray(labels).astype(int)
    if len(np.unique(labels)) < 2:
        raise ValueError(
            f"the learned combination needs true and false training pairs; got {len(labels)} pairs "
            f"all labelled {labels[:1]}: widen the train split"
        )
    model = make_pipeline(StandardScaler(), LogisticRegression(C=conf["C"], max_iter=1000))
    return model.fit(features.to_numpy(dtype=np.float64), labels)


# ------------------------------------------------------------- entry points --
def open_bench(
    results_dir: str | os.PathLike[str],
    method: str,
    output_dir: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None = None,
    progress: bool = True,
    overrides: dict[str, dict[str, Any]] | None = None,
    **split_options: Any,
) -> VerifierBench:
    """A ``VerifierBench`` on ``results_dir/method``'s cached matches, split with
    ``place_disjoint_split(**split_options)``; learned weights go to ``output_dir``."""
    scoring.readable_methods(results_dir, [method])  # what `results` refuses, the verifier notebooks refuse
    cached = verifier_inputs.CachedMatches(results_dir, method, cache_dir)
    pairs = cached.pairs.copy()
    pairs["split"] = verifier_inputs.place_disjoint_split(pairs, **split_options)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    return VerifierBench(cached, pairs, dict(split_options), output_dir, progress, dict(overrides or {}))


def write_results(results: pd.DataFrame, output_dir: str | os.PathLike[str], name: str = "verifiers.csv") -> Path:
    """Merge ``results`` into ``<output_dir>/verifiers.csv`` (rows of the same verifier, split and
    matches are replaced; others kept, so both notebooks add to one table)."""
    path = Path(output_dir) / name
    keys = ["verifier", "split", "matches"]
    if path.is_file():
        old = pd.read_csv(path, keep_default_na=False)
        fresh = set(map(tuple, results[keys].astype(str).to_numpy()))
        old = old[[tuple(r) not in fresh for r in old[keys].astype(str).to_numpy()]]
        results = pd.concat([old, results], ignore_index=True)
    atomic_write_csv(path, results)
    return path


def verifier_table(results: pd.DataFrame) -> pd.DataFrame:
    """AP and MR with their 95% CIs as text (%), one row a verifier, for people."""

    def cell(row: pd.Series, metric: str) -> str:
        if row.get("status") != "ok":
            return "-"
        return f"{100 * row[metric]:.1f} [{100 * row[f'{metric}_ci_low']:.1f}, {100 * row[f'{metric}_ci_high']:.1f}]"

    return pd.DataFrame(
        {
            "verifier": results["verifier"],
            "AP (%) [95% CI]": [cell(r, "ap") for _, r in results.iterrows()],
            "MR (%) [95% CI]": [cell(r, "max_recall") for _, r in results.iterrows()],
            "status": results["status"],
            "weights": results["weights"].fillna(""),
        }
    ).set_index("verifier")


def best_by(
    results: pd.DataFrame,
    boot: bootstrap.Bootstrap,
    metric: str = "max_recall",
    baseline: str = verifier_inputs.PAPER_VERIFIER,
) -> dict[str, Any]:
    """The verifier with the highest ``metric`` and its gain over ``baseline`` with a paired
    bootstrap 95% CI of the difference (same query resamples for both)."""
    ok = results[results["status"] == "ok"]
    winner = ok.loc[ok[metric].idxmax(), "verifier"]
    difference = (boot.samples[metric][winner] - boot.samples[metric][baseline]).dropna()
    low, high = np.percentile(difference, [2.5, 97.5]) if len(difference) else (np.nan, np.nan)
    estimate = float(ok.set_index("verifier").loc[winner, metric] - ok.set_index("verifier").loc[baseline, metric])
    return {
        "metric": metric,
        "winner": winner,
        "baseline": baseline,
        "difference": estimate,
        "difference_ci_low": float(low),
        "difference_ci_high": float(high),
        "winner_beats_baseline_share": float((difference > 0).mean()) if len(difference) else float("nan"),
    }
