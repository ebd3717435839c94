"""``python -m gvbench_nb explore [OUTPUT_DIR]``: JupyterLab on a working copy of explore_pairs.ipynb
in ``<OUTPUT_DIR>/explore/`` (its root), so autosave never touches the tracked notebook."""

from __future__ import annotations

import argparse
import json
import logging
import os
import secrets
import socket
import sys
from pathlib import Path
from typing import Any

from gvbench_nb.io_utils import add_described_command
from gvbench_nb.reporting.execute import NOTEBOOKS_DIR
from gvbench_nb.runner import config, method_outputs, runs, scoring

log = logging.getLogger(__name__)

SOURCE_NOTEBOOK = NOTEBOOKS_DIR / "explore_pairs.ipynb"
COPY_FOLDER = "explore"  # inside the run's folder: the working copy and the figures it writes
# A Jupyter config folder added to the search path of explore's JupyterLab only: its page config
# disables the announcements plugin, whose first-start pop-up asks to fetch Jupyter news.
LAB_CONFIG = Path(__file__).parent / "lab_config"
DEFAULT_PORT = 8888

HELP = "open JupyterLab on a working copy of the explore notebook, pointed at a finished run's folder"
DESCRIPTION = """\
Writes <OUTPUT_DIR>/explore/explore_pairs.ipynb, a copy of notebooks/explore_pairs.ipynb whose
parameters name that run (its params.resolved.yaml and folder), unless that copy exists (then it
is opened as you left it; delete it for a fresh one), and starts JupyterLab rooted in
<OUTPUT_DIR>/explore on it. Run All there: controls at the end redraw every view for another pick,
pair or method. The tracked notebooks are never written. Stop JupyterLab with Ctrl-C.
"""
EPILOG = """\
examples:
  python -m gvbench_nb explore                      # outputs/sample, after make demo
  python -m gvbench_nb explore outputs/gardens_point --no-browser --port 8890
"""


def check_run_folder(output_dir: Path) -> list[str]:
    """The methods a finished run's folder holds; a ``ResultsError`` (one sentence) when the
    folder is missing or is not the output folder of a finished ``run``."""
    if not output_dir.is_dir():
        raise method_outputs.ResultsError(
            f"{output_dir} is not a folder; give the output folder of a finished run "
            "(e.g. outputs/sample after make demo, or python -m gvbench_nb run params/sample.yaml)"
        )
    methods = scoring.readable_methods(output_dir)  # what `results` refuses, explore refuses, in its words
    if runs.resolved_params(output_dir) is None:
        raise method_outputs.ResultsError(
            f"{output_dir} has no {config.RESOLVED_PARAMS_NAME}, so it is not the output folder of a run; "
            "give the folder a run wrote (python -m gvbench_nb run PARAMS prints it)"
        )
    return methods


def working_notebook(output_dir: Path, source: Path = SOURCE_NOTEBOOK) -> dict[str, Any]:
    """``source`` with its parameters cell pointed at ``output_dir``'s run and every method it
    holds, outputs cleared and its jupytext pairing dropped (a copy has no twin to keep in step)."""
    notebook = json.loads(source.read_text(encoding="utf-8"))
    values = {
        "params_file": str(Path(str(runs.resolved_params(output_dir))).resolve()),
        "output_dir": str(output_dir.resolve()),
        "methods": None,
    }
    cells = notebook["cells"]
    parameters = [c for c in cells if "parameters" in c.get("metadata", {}).get("tags", [])]
    if len(parameters) != 1:
        raise ValueError(f"{source} has {len(parameters)} cells tagged 'parameters'; it needs exactly one")
    lines = "".join(parameters[0]["source"]).splitlines()
    for index, line in enumerate(lines):
        name = line.split("=", 1)[0].strip()
        if name in values and "=" in line:
            comment = line[line.index("#") :] if "#" in line else ""
            lines[index] = f"{name} = {values.pop(name)!r}" + (f"  {comment}" if comment else "")
    if values:
        raise ValueError(f"{source}'s parameters cell sets no {', '.join(values)}")
    parameters[0]["source"] = "\n".join(lines)
    for cell in cells:
        if cell["cell_type"] == "code":
            cell["outputs"], cell["execution_count"] = [], None
    notebook["metadata"].pop("jupytext", None)
    # What the kernel reports on start: a copy that says it already is not marked modified
    # before the user edits anything.
    notebook["metadata"].update(kernel_metadata())
    return notebook


def kernel_metadata() -> dict[str, Any]:
    """The notebook metadata JupyterLab writes when the python3 kernel starts: its kernelspec
    and the language_info ipykernel reports."""
    from ipykernel.ipkernel import IPythonKernel
    from jupyter_client.kernelspec import KernelSpecManager

    spec = KernelSpecManager().get_kernel_spec("python3")
    return {
        "kernelspec": {"display_name": spec.display_name, "language": spec.language, "name": "python3"},
        "language_info": dict(IPythonKernel.language_info),
    }


def prepare_copy(output_dir: Path, source: Path = SOURCE_NOTEBOOK) -> tuple[Path, bool]:
    """The working copy's path, and whether it was written now (False: it existed and is kept)."""
    from gvbench_nb.io_utils import atomic_write_text

    copy = output_dir / COPY_FOLDER / source.name
    if copy.exists():
        return copy, False
    copy.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(copy, json.dumps(working_notebook(output_dir, source), indent=1, ensure_ascii=False) + "\n")
    return copy, True


def port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def free_port(start: int = DEFAULT_PORT, tries: int = 50) -> int:
    """The first port from ``start`` that nothing listens on at localhost."""
    for port in range(start, start + tries):
        if port_is_free(port):
            return port
    raise method_outputs.ResultsError(f"no free port in {start}-{start + tries - 1}; pass --port with a free one")


def port_number(text: str) -> int:
    """``--port``: a TCP port, 1 to 65535."""
    try:
        port = int(text)
    except ValueError:
        port = 0
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port; give a number from 1 to 65535")
    return port


def lab_command(copy: Path, port: int, token: str, open_browser: bool) -> list[str]:
    """The JupyterLab command line: rooted in the copy's folder, opening the copy."""
    return [
        sys.executable,
        "-m",
        "jupyter",
        "lab",
        f"--ServerApp.root_dir={copy.parent}",
        f"--ServerApp.port={port}",
        "--ServerApp.port_retries=0",
        "--ServerApp.ip=127.0.0.1",
        f"--IdentityProvider.token={token}",
        f"--ServerApp.open_browser={open_browser}",
        # No news feed (None, not an empty URL: only None stops the pop-up asking to fetch news)
        # and no update check: the server asks no network.
        "--LabApp.news_url=None",
        "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate",
        # JupyterLab refuses root unless told; containers and CI often run as root.
        *(["--ServerApp.allow_root=True"] if hasattr(os, "geteuid") and os.geteuid() == 0 else []),
        str(copy),
    ]


def lab_url(copy: Path, port: int, token: str) -> str:
    return f"http://127.0.0.1:{port}/lab/tree/{copy.name}?token={token}"


def command_explore(args: argparse.Namespace) -> int:
    output_dir = Path(args.output_dir).resolve()
    methods = check_run_folder(output_dir)
    if args.port and not port_is_free(args.port):
        log.error(f"error: port {args.port} is in use on 127.0.0.1; give another --port or leave it out")
        return 2
    port = args.port or free_port()
    copy, written = prepare_copy(output_dir)
    token = secrets.token_hex(16)
    state = (
        "written now from notebooks/explore_pairs.ipynb"
        if written
        else "kept as you left it; delete it for a fresh one"
    )
    log.info(f"explore: {copy} ({state}); methods {', '.join(methods)}")
    log.info(f"JupyterLab: {lab_url(copy, port, token)} (Ctrl-C stops it)")
    command = lab_command(copy, port, token, open_browser=not args.no_browser)
    search = os.pathsep.join(filter(None, [str(LAB_CONFIG), os.environ.get("JUPYTER_CONFIG_PATH")]))
    # JupyterLab takes this process over: Ctrl-C and signals reach it.
    os.execve(command[0], command, {**os.environ, "JUPYTER_CONFIG_PATH": search})
    return 0  # not reached


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Register ``explore`` on the CLI's subcommands."""
    parser = add_described_command(subparsers, "explore", HELP, DESCRIPTION, EPILOG)
    parser.add_argument(
        "output_dir",
        nargs="?",
        default=str(config.outputs_path(config.OUTPUTS_DIR / "sample")),
        metavar="OUTPUT_DIR",
        help="a finished run's output folder (default: outputs/sample, which make demo writes)",
    )
    parser.add_argument(
        "--port", type=port_number, help=f"JupyterLab's port (default: the first free from {DEFAULT_PORT})"
    )
    parser.add_argument("--no-browser", action="store_true", help="do not open a browser; open the printed URL")
    parser.set_defaults(handler=command_explore)
