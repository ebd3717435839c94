"""What the notebooks share before they plot: a sequence, written results or a verifier bench.
Missing results raise ``ResultsMissingError`` naming the command, unless ``compute_missing=True``."""

from __future__ import annotations

import ast
import os
import shlex
import types
import typing
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import pandas as pd

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import unknown_keys_hint
from gvbench_nb.runner import config, runs, scoring, sequence_build

if TYPE_CHECKING:
    from gvbench_nb.studies.alternative_verifiers import VerifierBench

# `run_tables` and `alternative_verifiers` pull in OpenCV and scikit-learn: imported where they are used,
# so a stage notebook that only loads a sequence stays light.

PathLike = str | os.PathLike[str]
# The params file a stage notebook reads when given none (where JupyterLab and nbmake run it with its defaults).
DEFAULT_PARAMS_FILE = config.PROJECT_ROOT / "params" / "sample.yaml"
# load_params keys a notebook may override -> the `run` option that does the same.
RUN_OPTIONS = {"output_dir": "--output-dir", "profile": "--profile", "limit": "--limit"}


class ResultsMissingError(GVBenchError, FileNotFoundError):
    """Results a notebook reads are not there (and it did not ask to compute them)."""


class AnalysisInputs(NamedTuple):
    output_dirs: list[str]  # the sequence output folders, as given
    results: pd.DataFrame  # the table of the runs they show, one table with an output_dir column
    figures: Path  # where the notebook writes its figures and tables (created)


class ParameterError(GVBenchError, TypeError):
    """A notebook parameter its parameters cell does not declare, or of another type than it declares."""


def _accepts(annotation: Any, value: Any) -> bool:
    """Whether ``value`` is of the parameters cell's ``annotation`` (an int is a number too, a bool is not)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_accepts(member, value) for member in typing.get_args(annotation))
    kind = typing.get_origin(annotation) or annotation
    if kind in (int, float):
        return isinstance(value, (int, float) if kind is float else int) and not isinstance(value, bool)
    return isinstance(value, kind) if isinstance(kind, type) else True


_KINDS = {list: "a list", dict: "a mapping", str: "text", int: "a whole number", float: "a number"}
_KINDS.update({bool: "True or False", type(None): "None"})


def injected_names(namespace: dict[str, Any]) -> list[str]:
    """The names papermill's injected cell (``# Parameters``, in the kernel's history ``In``) assigns."""
    cells = [ast.parse(source) for source in namespace.get("In", ()) if source.startswith("# Parameters")]
    assigned = [
        target for cell in cells for node in cell.body if isinstance(node, ast.Assign) for target in node.targets
    ]
    return [target.id for target in assigned if isinstance(target, ast.Name)]


def check_parameters(namespace: dict[str, Any]) -> None:
    """Refuse, in one sentence, a parameter papermill passed that the notebook's parameters cell does
    not declare, and one of another type than its annotation, in the notebook's ``globals()``:
    papermill's ``-p`` passes text, so a list or a mapping is given with ``-y``."""
    declared = list(namespace.get("__annotations__", {}))
    unknown = [name for name in injected_names(namespace) if name not in declared]
    if unknown:
        raise ParameterError(
            f"unknown notebook parameter(s) {unknown_keys_hint(unknown, declared)}; this notebook's: {', '.join(declared)}"
        )
    for name, annotation in namespace.get("__annotations__", {}).items():
        value = namespace.get(name)
        if name not in namespace or _accepts(annotation, value):
            continue
        union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
        members = typing.get_args(annotation) if union else (annotation,)
        expected = " or ".join(_KINDS.get(typing.get_origin(m) or m, str(m)) for m in members)
        message = f"notebook parameter {name} must be {expected}, got {value!r}"
        wanted = next(
            (kind for kind in (list, dict) if any((typing.get_origin(m) or m) is kind for m in members)), None
        )
        if isinstance(value, str) and wanted is not None:
            brackets = "[]" if wanted is list else "{}"
            text = value if value.strip()[:1] == brackets[0] else f"{brackets[0]}{value}{brackets[1]}"
            message += (
                f": papermill's -p passes text, give {expected} with -y, e.g. -y {shlex.quote(f'{name}: {text}')}"
            )
        raise ParameterError(message)


def as_list(value: PathLike | Iterable[PathLike] | None) -> list[str]:
    """One path or a list of them, as code passes them (a notebook declaring a list refuses a string)."""
    if value is None:
        return []
    if isinstance(value, (str, os.PathLike)):
        return [os.fspath(value)]
    return [os.fspath(v) for v in value]


def run_command_line(params_file: PathLike, methods: SequenceType[str], **overrides: Any) -> str:
    """The shell command that runs ``methods`` with the params file, with an option for each
    override that changes what the file says."""
    as_written = config.load_params(params_file)
    words = ["python", "-m", "gvbench_nb", "run", as_written["params_file"], "--methods", ",".join(methods)]
    for key, value in overrides.items():
        if value is None:
            continue
        value = str(Path(value).resolve()) if key == "output_dir" else str(value)
        if value != str(as_written[key]):
            words += [RUN_OPTIONS[key], value]
    return shlex.join(words)


def missing_methods(output_dir: PathLike, methods: SequenceType[str]) -> list[str]:
    """The ``methods`` (names or ``all``/``all-available``) without a ``pairs.csv`` in ``output_dir``;
    a method the folder holds is never missing, though its name is the registry's or not (an import)."""
    held = set(scoring.methods_with_results(Path(output_dir)))
    return [m for m in method_registry.expand_methods([m for m in methods if m not in held]) if m not in held]


def params_keys(namespace: dict[str, Any]) -> dict[str, Any]:
    """The params-file keys a notebook's parameters set (not None), from its ``globals()``, whose
    parameters are checked first (``check_parameters``)."""
    check_parameters(namespace)
    keys = [*config.REQUIRED_KEYS, *config.OPTIONAL_KEYS]
    return {key: namespace[key] for key in keys if namespace.get(key) is not None}


def shipped_params_file(sequence: str) -> Path | None:
    """The repository's params file (``params/*.yaml``) of ``sequence``, if any."""
    files = sorted(DEFAULT_PARAMS_FILE.parent.glob("*.yaml"))
    return next((p for p in files if config.read_yaml_mapping(p).get("sequence") == sequence), None)


def load_params(params_file: PathLike | None, **keys: Any) -> dict[str, Any]:
    """``params_file`` with ``keys`` (not None) replacing its own. Without it, keys naming a
    repository params file's sequence and setting every key that file sets (``papermill -f
    params/NAME.yaml``) read as that file; any other keys holding every required one (``-f ANY.yaml``)
    are the params, relative paths read from the working folder; fewer keys replace those of their
    sequence's repository file, else of params/sample.yaml."""
    given = {key: value for key, value in keys.items() if value is not None}
    if params_file is None and "sequence" in given:
        config.check_value("sequence", given["sequence"], "the notebook's parameters")
        shipped = shipped_params_file(given["sequence"])
        whole = all(key in given for key in config.REQUIRED_KEYS)
        if whole and (shipped is None or not set(config.read_yaml_mapping(shipped)) <= set(given)):
            folder, given_file = Path.cwd(), papermill_params_file()
            print(f"params: the notebook's parameters (no params_file); relative paths are read from {folder}")
            return config.resolve_params(given, str(given_file or "the notebook's parameters"), folder)
        if shipped is None:
            missing = [key for key in config.REQUIRED_KEYS if key not in given]
            raise config.ParamsError(
                f"the notebook's parameters lack {', '.join(missing)}, and no params file in "
                f"{DEFAULT_PARAMS_FILE.parent} is of sequence {given['sequence']!r}: give every key "
                "(-f PARAMS.yaml), or the params file of these parameters (-p params_file PATH)"
            )
        params_file = shipped
        print(f"params: {shipped} with the notebook's parameters; relative paths are read from {shipped.parent}")
    if params_file and not Path(params_file).exists() and runs.is_run(Path(params_file).parent):
        run = Path(params_file).parent  # ``run`` names its params in the finished run: read where it is built
        params_file = run.with_name(runs.BUILDING + run.name) / Path(params_file).name
    return config.load_params(params_file or DEFAULT_PARAMS_FILE, **given)


def papermill_params_file() -> Path | None:
    """The params file ``papermill -f`` gave this kernel (its parent's command line, the last -f), else None."""
    import psutil

    try:
        parent = psutil.Process().parent()
        words, folder = (parent.cmdline(), parent.cwd()) if parent else ([], "")
    except psutil.Error:
        return None
    given = [value for flag, value in zip(words, words[1:]) if flag in ("-f", "--parameters_file")]
    return Path(folder, given[-1]).resolve() if given and "papermill" in " ".join(words[:3]) else None


def start_run(params: dict[str, Any], name: str) -> Path:
    """The run stage notebook ``name`` writes into: the run executing it, else one of its own (``finish_run``)."""
    if runs.is_run(params["output_dir"]):
        return Path(params["output_dir"])
    building = runs.start(params["output_dir"], name)
    config.write_resolved_params(params, building, f"notebooks/{name}.ipynb")
    return building


def finish_run(params: dict[str, Any], run: Path) -> Path:
    """``run``, finished (every file of it written) when ``start_run`` began it."""
    if runs.is_run(params["output_dir"]):
        return run
    finished = runs.finish(run)
    scoring.refresh_view(params["output_dir"])
    print(f"added run {finished.name} to {params['output_dir']}")
    return finished


def final_path(path: PathLike) -> Path:
    """``path``, when in a run being built, by its place in the finished run (what an executed notebook keeps)."""
    path = Path(path)
    run = next((folder for folder in (path, *path.parents) if runs.is_run(folder)), None)
    return path if run is None else run.with_name(str(runs.run_id(run))) / path.relative_to(run)


def load_sequence(params_file: PathLike | None, **overrides: Any) -> tuple[dict[str, Any], Sequence]:
    """The params (``load_params``) and their sequence; the pair file is made first when the
    params build it (``sequence_build.prepare_sequence``)."""
    params = load_params(params_file, **overrides)
    sequence = sequence_build.prepare_sequence(params)
    runs.claim(params["output_dir"])  # the notebook writes its figures and tables there
    return params, sequence


def require_results(
    params_file: PathLike,
    methods: SequenceType[str] = ("sift-nn",),
    compute_missing: bool = False,
    evaluate: bool = True,
    **overrides: Any,
) -> Path:
    """The params' output folder, checked to hold ``methods``' results; ``compute_missing=True`` runs
    what is missing (and, with ``evaluate``, writes the folder's results.csv for people), else
    ``ResultsMissingError``. Readers derive the table from the runs, never from results.csv."""
    params = config.load_params(params_file, **overrides)
    output_dir = Path(params["output_dir"])
    missing = missing_methods(output_dir, methods)
    if not missing:
        return output_dir
    if not compute_missing:
        raise ResultsMissingError(
            f"{output_dir} has no results of {', '.join(missing)}: make them with "
            f"`{run_command_line(params_file, missing, **overrides)}`, or pass compute_missing=True to run them here."
        )
    from gvbench_nb.runner import method_runs

    sequence = sequence_build.prepare_sequence(params)
    for method in missing:
        method_runs.run_method_of_params(params, sequence, method)
    if evaluate:
        scoring.refresh_view(output_dir)
    return output_dir


def load_results(
    output_dirs: PathLike | Iterable[PathLike],
    figures_dir: PathLike,
    params_files: PathLike | Iterable[PathLike] | None = (),
    methods: SequenceType[str] = ("sift-nn",),
    compute_missing: bool = False,
) -> AnalysisInputs:
    """The table of the runs ``output_dirs`` show, each of ``params_files`` first checked by
    ``require_results`` (``[]``, as the report passes, checks nothing)."""
    from gvbench_nb.evaluation import run_tables

    folders = [os.fspath(config.outputs_path(folder)) for folder in as_list(output_dirs)]
    for params_file in as_list(params_files):
        require_results(params_file, methods, compute_missing=compute_missing)
    results = run_tables.load_results(folders)  # refuses what `results` refuses, before a figure folder is made
    figures = config.outputs_path(figures_dir)
    figures.mkdir(parents=True, exist_ok=True)
    return AnalysisInputs(folders, results, figures)


def table(
    frame: pd.DataFrame, precision: int = 3, percent: SequenceType[str] = (), labels: dict[str, str] | None = None
) -> Any:
    """A table as a notebook's page shows it: without pandas' row numbers, headers in words, AP, MR
    and the ``percent`` columns in % (one decimal), other numbers rounded, methods by ``labels``."""
    from gvbench_nb.evaluation import run_tables

    shown = run_tables.readable_table(frame, percent, labels)
    in_percent = [c for c in shown.columns if str(c).endswith("(%)")]
    style = shown.style.hide(axis="index").format(precision=precision, na_rep="-")
    return style.format(precision=1, subset=in_percent, na_rep="-")


def sequence_of(results: pd.DataFrame, output_dir: PathLike) -> str:
    """The sequence name the runs in ``output_dir`` recorded (a row of ``load_results``)."""
    names = results.loc[results["output_dir"] == str(Path(output_dir)), "sequence"]
    if names.empty:
        raise ResultsMissingError(
            f"{output_dir} is not among the loaded output folders "
            f"({', '.join(results['output_dir'].unique())}); add it to output_dirs"
        )
    return str(names.iloc[0])


def open_verifier_bench(
    results_dir: PathLike,
    method: str,
    output_dir: PathLike,
    *,
    params_file: PathLike | None = None,
    profile: str | None = None,
    cache_dir: PathLike | None = None,
    compute_missing: bool = False,
    classifier: dict[str, Any] | None = None,
    **split_options: Any,
) -> VerifierBench:
    """A ``VerifierBench`` on ``results_dir/method``'s cached matches (``results_dir`` relative to the
    notebook); ``classifier`` overrides the in-domain Doppelgangers training."""
    results_dir, output_dir = config.outputs_path(Path(results_dir).resolve()), config.outputs_path(output_dir)
    if params_file:
        require_results(
            params_file,
            [method],
            compute_missing=compute_missing,
            evaluate=False,
            output_dir=str(results_dir),
            profile=profile,
        )
    elif missing_methods(results_dir, [method]):
        raise ResultsMissingError(
            f"{results_dir} has no results of {method}: run it on that sequence first "
            f"(python -m gvbench_nb run PARAMS --methods {method} --output-dir {results_dir})"
        )
    from gvbench_nb.studies import alternative_verifiers

    overrides = {"doppelgangers-in-domain": dict(classifier)} if classifier else None
    return alternative_verifiers.open_bench(
        results_dir, method, output_dir, cache_dir, overrides=overrides, **split_options
    )


def quartiles_by_label(
    table: pd.DataFrame, columns: SequenceType[str] = ("num_matches", "num_inliers")
) -> pd.DataFrame:
    """``describe()`` of a pair table's ``columns`` for false (0) and true (1) pairs, a row a
    statistic: whole numbers as integers (a count of 1006, not 1006.000000), the others to one decimal."""
    summary = table.groupby("label")[list(columns)].describe().transpose()
    return summary.map(lambda v: int(v) if float(v).is_integer() else round(float(v), 1))
