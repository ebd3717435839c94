"""How long the condition sweep's renderer takes: one query traversal per condition setting
(``speed_bench.print_render_time``)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from collections.abc import Sequence as SequenceType
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.data import synthetic

RENDER_SETTINGS: dict[str, dict[str, float]] = {
    "clear": {},
    **{condition: {condition: 1.0} for condition in synthetic.CONDITIONS},
    "all three": dict.fromkeys(synthetic.CONDITIONS, 1.0),
}


RENDER_TIME_COLUMNS = ["setting", "conditions", "n_frames", "image_size", "repeats", "median_seconds", "min_seconds"]
RENDER_TIME_COLUMNS += ["max_seconds", "scene_seconds", "workers", "cpu_count", "loadavg_1m"]


def time_render(
    n_frames: int = 100,
    image_size: SequenceType[int] = (640, 480),
    seed: int = 0,
    repeats: int = 3,
    settings: Mapping[str, Mapping[str, float]] | None = None,
    workers: int | None = None,
) -> pd.DataFrame:
    """Seconds to render one ``n_frames`` query traversal per condition setting (strength 1), PNG
    writing not counted, the scene timed apart; the load average beside each row (a busy machine is slower)."""
    started = time.perf_counter()
    route = synthetic.make_route(seed=seed, n_frames=n_frames, image_size=(int(image_size[0]), int(image_size[1])))
    scene_seconds = time.perf_counter() - started
    rows = []
    for name, conditions in (settings or RENDER_SETTINGS).items():
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            synthetic.render_traversal(
                route.scene, route.query, route.K, route.image_size, conditions, seed, 1, workers=workers
            )
            seconds.append(time.perf_counter() - start)
        cpus = os.cpu_count()
        values: list[Any] = [name, json.dumps(dict(conditions)), n_frames, f"{image_size[0]}x{image_size[1]}", repeats]
        values += [float(np.median(seconds)), min(seconds), max(seconds), scene_seconds, workers or min(4, cpus or 1)]
        rows.append(dict(zip(RENDER_TIME_COLUMNS, [*values, cpus, round(os.getloadavg()[0], 2)])))
    return pd.DataFrame(rows)
