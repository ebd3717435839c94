"""Executing a notebook with papermill: how `run` and `report` keep each notebook as the record of its step."""

from __future__ import annotations

import contextlib
import functools
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gvbench_nb import GVBenchError
from gvbench_nb.io_utils import WRITE_FAILURES, WriteFailedError

if TYPE_CHECKING:
    from jupyter_client.manager import KernelManager

NOTEBOOKS_DIR = Path(__file__).resolve().parents[2] / "notebooks"
KERNEL_NAME = "python3"
# What every stage notebook's setup cell imports; a started kernel loads them while it waits.
PRELOAD = ("pandas", "matplotlib.pyplot", "gvbench_nb.runner.method_runs", "gvbench_nb.evaluation.plots")


class KernelPool:
    """Fresh kernels (``count`` in all, at most ``ahead`` waiting) started, with ``preload`` imported,
    while the run still computes; each notebook still gets a kernel of its own."""

    def __init__(self, count: int, ahead: int = 3, preload: tuple[str, ...] = PRELOAD):
        self._preload = preload
        self._lock = threading.Lock()
        self._waiting: list[KernelManager] = []
        self._to_start = count
        for _ in range(min(ahead, count)):
            self._start_one()

    def _start_one(self) -> None:
        self._to_start -= 1
        manager = new_kernel_manager()
        try:
            manager.start_kernel(cwd=str(NOTEBOOKS_DIR), extra_arguments=preload_arguments(self._preload))
        except Exception:  # papermill then starts the notebook's kernel itself, and reports any error
            return
        self._waiting.append(manager)

    def take(self) -> KernelManager | None:
        """A started kernel (and another started in its place while more are due), or None."""
        with self._lock:
            if not self._waiting:
                return None
            manager = self._waiting.pop(0)
            if self._to_start > 0:
                self._start_one()
            return manager

    def shutdown(self) -> None:
        """Stop the kernels no notebook took (a finished or failed run)."""
        with self._lock:
            waiting, self._waiting, self._to_start = self._waiting, [], 0
        for manager in waiting:
            stop_kernel(manager)


@functools.cache
def _client_recording_manager() -> type[KernelManager]:
    """A KernelManager remembering its clients, whose channels nbclient leaves open: ``stop_kernel`` closes them."""
    from jupyter_client.manager import KernelManager

    class ClientRecordingKernelManager(KernelManager):
        def client(self, **kwargs: Any) -> Any:
            client = super().client(**kwargs)
            self.__dict__.setdefault("issued_clients", []).append(client)
            return client

    return ClientRecordingKernelManager


def transport_encryption() -> str:
    """CurveZMQ to the kernels where pyzmq has it: it also spares each kernel's "without encryption" warning."""
    import zmq

    return "auto" if zmq.has("curve") else "disabled"


def new_kernel_manager() -> KernelManager:
    """A kernel manager for one notebook's kernel (not started yet)."""
    return _client_recording_manager()(kernel_name=KERNEL_NAME, transport_encryption=transport_encryption())


# tqdm.auto (imported by huggingface_hub, under vismatch in .venv-imm) warns in a kernel without
# ipywidgets, then draws its plain bar anyway; the bars go to the terminal, not to widgets.
QUIET_WARNINGS = "__import__('warnings').filterwarnings('ignore', 'IProgress not found')"


def preload_arguments(modules: tuple[str, ...]) -> list[str]:
    """Kernel arguments that silence ``QUIET_WARNINGS`` and import ``modules`` (binding nothing, not
    even ``_``), with the history in memory."""
    imports = f" or list(map(__import__, {tuple(modules)!r})).clear()" if modules else ""
    # History in memory: a batch kernel keeps none, and kernels running at once then never
    # contend for (or, on a full disk, fail to write) the one history file.
    return [f"--IPKernelApp.exec_lines={QUIET_WARNINGS}{imports}", "--HistoryManager.hist_file=:memory:"]


def stop_kernel(manager: KernelManager) -> None:
    for client in manager.__dict__.get("issued_clients", []):
        with contextlib.suppress(Exception):
            client.stop_channels()
    with contextlib.suppress(Exception):  # already gone
        manager.shutdown_kernel(now=True)


_pool: KernelPool | None = None


@contextlib.contextmanager
def kernels_ahead(count: int) -> Iterator[KernelPool]:
    """While the block runs, ``execute_notebook`` takes its kernels from a ``KernelPool`` of
    ``count`` kernels; the ones left are stopped at the end."""
    global _pool
    pool = KernelPool(count)
    _pool = pool
    try:
        yield pool
    finally:
        _pool = None
        pool.shutdown()


# A new kernel's ports are found free, then bound by the kernel: another process starting one at
# the same moment can take a port in between, and the kernel dies before it answers. Nothing of
# the notebook ran then, so it is started again on a fresh kernel.
KERNEL_START_TRIES = 3


def execute_notebook(name: str, output_path: Path, parameters: dict[str, Any]) -> None:
    output_path.parent.mkdir(parents=True, exist_ok=True)
    # A pooled kernel, else one nbclient starts and leaves running (stopped below).
    manager = (_pool.take() if _pool is not None else None) or new_kernel_manager()
    try:
        for attempt in range(1, KERNEL_START_TRIES + 1):
            try:
                _execute_on(manager, name, output_path, parameters)
                return
            except RuntimeError as error:
                if "before replying to kernel_info" not in str(error) or attempt == KERNEL_START_TRIES:
                    raise
                stop_kernel(manager)
                manager = new_kernel_manager()
    finally:  # nbclient stops only the kernels of managers it made
        stop_kernel(manager)


def _execute_on(manager: KernelManager, name: str, output_path: Path, parameters: dict[str, Any]) -> None:
    # jsonschema would compile rfc3987-syntax's IRI grammar at import (more CPU than papermill's
    # import) for a format no notebook schema uses.
    sys.modules.setdefault("rfc3987_syntax", None)  # type: ignore[arg-type]
    import papermill

    try:
        # Kernel stderr (the tqdm bars) goes to the terminal; the kernel starts in notebooks/ through
        # nbclient's resources, not papermill's cwd, which would change this whole (threaded) process's folder.
        papermill.execute_notebook(
            str(NOTEBOOKS_DIR / name),
            str(output_path),
            parameters=parameters,
            resources={"metadata": {"path": str(NOTEBOOKS_DIR)}},
            progress_bar=False,
            stderr_file=sys.stderr,
            kernel_name=KERNEL_NAME,
            km=manager,
            extra_arguments=preload_arguments(()),  # a kernel nbclient starts: the same quiet warnings
        )
    except papermill.PapermillExecutionError as failure:
        raise NotebookFailedError(failure.ename, failure.evalue, failure.exec_count) from failure
    except OSError as error:  # papermill writing the executed notebook names no file
        if error.errno not in WRITE_FAILURES or error.filename:
            raise
        raise WriteFailedError(
            error.errno,
            f"cannot write {output_path} ({error.strerror}); free disk space (or raise the quota or file "
            "size limit) and run again",
        ) from error


def _user_error_names() -> set[str]:
    """The names of every loaded ``GVBenchError`` class (a notebook's error arrives by name)."""
    found, todo = set(), [GVBenchError]
    while todo:
        for sub in todo.pop().__subclasses__():
            found.add(sub.__name__)
            todo.append(sub)
    return found


class NotebookFailedError(GVBenchError):
    """A notebook's cell raised: a user error reads as outside a notebook; any other exits 1."""

    def __init__(self, ename: str, evalue: str, exec_count: int | None) -> None:
        self.ename, self.evalue = ename, evalue
        if ename in _user_error_names():
            message = f"{evalue} (the executed notebook in the output folder keeps the traceback)"
        else:
            self.exit_code = 1
            message = (
                f"in cell {exec_count}: {ename}: {evalue}\n"
                "the executed notebook (with the full traceback) is in the output folder"
            )
        super().__init__(message)
