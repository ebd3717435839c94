"""Progress bars that fit where they run: a widget in JupyterLab, a bar redrawn in a terminal,
and in a file or a batch-executed notebook (papermill, nbmake) a line every half minute at most,
so a log or an executed notebook holds a few lines a bar rather than one an update."""

from __future__ import annotations

import os
import sys
from typing import Any

BATCH_INTERVAL_SECONDS = 30.0


def interactive_kernel() -> bool:
    """True in a kernel that a Jupyter server started for a notebook (it sets JPY_SESSION_NAME);
    false in a terminal and in papermill's or nbmake's kernels."""
    return "ipykernel" in sys.modules and "JPY_SESSION_NAME" in os.environ


def progress_bar(iterable: Any = None, **options: Any) -> Any:
    """``tqdm(iterable, **options)`` for where it runs: ``tqdm.auto`` (a widget) in JupyterLab;
    elsewhere plain tqdm, redrawn at most every ``BATCH_INTERVAL_SECONDS`` unless it writes to a terminal."""
    if interactive_kernel():
        from tqdm.auto import tqdm as auto_tqdm

        return auto_tqdm(iterable, **options)
    from tqdm import tqdm

    stream = options.get("file") or sys.stderr
    if not getattr(stream, "isatty", lambda: False)():
        options.setdefault("mininterval", BATCH_INTERVAL_SECONDS)
    return tqdm(iterable, **options)
