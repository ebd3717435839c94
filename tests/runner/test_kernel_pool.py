"""Kernels started ahead of a run's notebooks: each notebook still gets a fresh kernel of its
own, started in notebooks/, and no kernel outlives the run, whether it finishes or fails."""

from __future__ import annotations

import json

import nbformat
import pytest

from gvbench_nb.reporting import execute

pytestmark = pytest.mark.reliability


def _alive(manager) -> bool:
    return bool(manager.is_alive())


def test_pool_starts_ahead_hands_each_kernel_out_once_and_stops_the_rest():
    pool = execute.KernelPool(count=3, ahead=2)
    try:
        first = pool.take()
        second = pool.take()
        assert first is not None and second is not None and first is not second
        assert _alive(first) and _alive(second)
        third = pool.take()  # started when the first was taken
        assert third is not None and third not in (first, second)
        assert pool.take() is None  # three in all
    finally:
        pool.shutdown()
        for manager in (first, second, third):
            execute.stop_kernel(manager)
    assert not any(_alive(m) for m in (first, second, third))


def test_kernels_left_untaken_are_stopped_when_the_run_fails():
    with pytest.raises(RuntimeError, match="a notebook failed"), execute.kernels_ahead(2) as pool:
        waiting = list(pool._waiting)
        assert len(waiting) == 2 and all(_alive(m) for m in waiting)
        raise RuntimeError("a notebook failed")
    assert not any(_alive(m) for m in waiting)
    assert execute._pool is None


def test_a_notebook_runs_in_a_started_kernel_in_the_notebooks_folder_which_is_then_stopped(tmp_path, monkeypatch):
    monkeypatch.setattr(execute, "NOTEBOOKS_DIR", tmp_path)
    notebook = nbformat.v4.new_notebook()
    parameters = nbformat.v4.new_code_cell("out = ''")
    parameters.metadata["tags"] = ["parameters"]
    notebook.cells = [
        parameters,
        nbformat.v4.new_code_cell(
            "import json, os, sys, types\n"
            "modules = sorted(k for k, v in globals().items() if isinstance(v, types.ModuleType) and not k.startswith('__'))\n"
            "open(out, 'w').write(json.dumps({'pid': os.getpid(), 'cwd': os.getcwd(), 'loaded': 'pandas' in sys.modules,"
            " 'modules_named': modules, 'last_result': repr(globals().get('_'))}))"
        ),
    ]
    notebook.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(notebook, tmp_path / "tiny.ipynb")
    with execute.kernels_ahead(1) as pool:
        manager = pool._waiting[0]
        pid = manager.provisioner.process.pid
        execute.execute_notebook("tiny.ipynb", tmp_path / "out" / "tiny.ipynb", {"out": str(tmp_path / "where.json")})
        assert not _alive(manager)  # stopped once its notebook finished
    wrote = json.loads((tmp_path / "where.json").read_text())
    # The preloaded modules are loaded, but the notebook's namespace holds only what its cells made.
    assert wrote == {
        "pid": pid,
        "cwd": str(tmp_path),
        "loaded": True,
        "modules_named": ["json", "os", "sys", "types"],
        "last_result": "''",
    }
    assert (tmp_path / "out" / "tiny.ipynb").is_file()


def test_kernels_run_encrypted_and_print_no_transport_or_iprogress_warning(tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(execute, "NOTEBOOKS_DIR", tmp_path)
    notebook = nbformat.v4.new_notebook()
    parameters = nbformat.v4.new_code_cell("out = ''")
    parameters.metadata["tags"] = ["parameters"]
    # tqdm.auto in a kernel without ipywidgets (as in .venv-imm, where huggingface_hub imports it)
    without_widgets = "import sys\nsys.modules['ipywidgets'] = None\nimport tqdm.auto"
    notebook.cells = [
        parameters,
        nbformat.v4.new_code_cell(without_widgets),
        nbformat.v4.new_code_cell("open(out, 'w').write('ran')"),
    ]
    notebook.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(notebook, tmp_path / "tiny.ipynb")
    with execute.kernels_ahead(1) as pool:  # a started kernel from the pool
        assert pool._waiting[0].curve_publickey is not None  # CurveZMQ keys provisioned
        execute.execute_notebook("tiny.ipynb", tmp_path / "pooled.ipynb", {"out": str(tmp_path / "pooled.txt")})
    execute.execute_notebook("tiny.ipynb", tmp_path / "alone.ipynb", {"out": str(tmp_path / "alone.txt")})
    assert (tmp_path / "pooled.txt").read_text() == (tmp_path / "alone.txt").read_text() == "ran"
    printed = capfd.readouterr()
    assert "without encryption" not in printed.err + printed.out
    for executed in ("pooled.ipynb", "alone.ipynb"):
        outputs = [o for c in nbformat.read(tmp_path / executed, as_version=4).cells for o in c.get("outputs", [])]
        assert "IProgress" not in json.dumps(outputs), executed


@pytest.mark.parametrize(
    ("failures", "message", "calls", "raises"),
    [
        (1, "Kernel died before replying to kernel_info", 2, False),  # a port taken between pick and bind
        (9, "Kernel died before replying to kernel_info", execute.KERNEL_START_TRIES, True),
        (1, "something else", 1, True),  # any other error is not retried
    ],
)
def test_a_kernel_that_dies_before_answering_is_replaced_and_each_kernel_stopped(
    monkeypatch, tmp_path, failures, message, calls, raises
):
    import papermill

    managers, stopped = [], []

    def execute_notebook(*args, km, **kwargs):
        managers.append(km)
        if len(managers) <= failures:
            raise RuntimeError(message)

    monkeypatch.setattr(papermill, "execute_notebook", execute_notebook)
    monkeypatch.setattr(execute, "stop_kernel", stopped.append)
    if raises:
        with pytest.raises(RuntimeError, match=message):
            execute.execute_notebook("01_sequence.ipynb", tmp_path / "out.ipynb", {})
    else:
        execute.execute_notebook("01_sequence.ipynb", tmp_path / "out.ipynb", {})
    assert len(managers) == calls and len({id(m) for m in managers}) == calls  # a fresh kernel each try
    assert stopped == managers  # each stopped once
