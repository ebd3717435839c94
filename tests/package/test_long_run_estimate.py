"""A run estimated over five minutes says so first, with its estimate: Gardens Point's shipped params
(about six minutes on a 2-core CPU by the measured costs) do; the sample's fast methods do not."""

from __future__ import annotations

import pytest

from gvbench_nb.runner import config, run_estimate, sequence_build


def note_of(name: str, tmp_path, **overrides) -> str | None:
    params = config.load_params(
        config.PROJECT_ROOT / "params" / f"{name}.yaml", output_dir=str(tmp_path / name), **overrides
    )
    return run_estimate.long_run_note(
        params | {"cache_dir": str(tmp_path / "cache")}, sequence_build.prepare_sequence(params)
    )


@pytest.mark.reliability
def test_gardens_points_params_say_their_estimate_first_and_the_demo_does_not(shared_data, tmp_path):
    note = note_of("gardens_point", tmp_path)
    assert note is not None and note.startswith("note: this run is estimated at 6 minutes ("), note
    assert note_of("sample", tmp_path, methods="sift-nn,orb-nn,xfeat-nn") is None
