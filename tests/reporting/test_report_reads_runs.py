"""The report reads the runs, never the folder's results.csv (written for people), and its index says
what `results` says beside its table: the methods the view leaves out and the collapsed-inlier line."""

from __future__ import annotations

import argparse
import html
import re

import pandas as pd
import pytest
from written_runs import add_run

from gvbench_nb import cli
from gvbench_nb.reporting import report
from gvbench_nb.runner import scoring

ENVIRONMENT = {"device": "cpu", "device_name": "cpu", "cpu_count": 1, "torch": "-", "kornia": "-", "opencv": "-"}


def toy_table(scores: list[int], collapsed: bool = False) -> pd.DataFrame:
    """Four queries of one true and one false pair; with ``collapsed`` the top false pair's inliers
    fall on 1 reference keypoint."""
    table = pd.DataFrame(
        {
            "pair_index": range(8),
            "query": [f"q{i // 2}" for i in range(8)],
            "reference": [f"r{i}" for i in range(8)],
            "label": [1, 0] * 4,
            "score": scores,
        }
    )
    table["num_inliers"] = table["num_matches"] = table["score"]
    table["num_inlier_keypoints_query"] = table["num_inlier_keypoints_reference"] = table["score"]
    if collapsed:
        table.loc[table["score"].where(table["label"] == 0).idxmax(), "num_inlier_keypoints_reference"] = 1
    return table.assign(extract_seconds=0.1, match_seconds=0.1, verify_seconds=0.1)


def write_run(folder, method: str, table: pd.DataFrame, profile: str, **record) -> None:
    conf = {"paper_name": method.upper(), "profile": profile}
    record = {"sequence": "toy", "environment": ENVIRONMENT, "finished_at": "2026-12-07", "conf": conf, **record}
    add_run(folder, method, table, record)


def page(tmp_path, folder) -> str:
    """The index over ``folder``, with the intervals table the uncertainty notebook writes."""
    report_dir = tmp_path / "report"
    (report_dir / folder.name).mkdir(parents=True, exist_ok=True)
    intervals = {"metric": "ap", "estimate": 0.5, "low": 0.25, "high": 0.75, "n_valid": 100}
    pd.DataFrame([{"method": m, **intervals} for m in ("sift-nn", "orb-nn")]).to_csv(
        report_dir / folder.name / "bootstrap_intervals.csv", index=False
    )
    return html.unescape(report.summary_page(report_dir, [folder], []))


def parse(*words: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    report.add_command(parser.add_subparsers(dest="command"))
    return parser.parse_args(["report", *words])


@pytest.mark.reliability
@pytest.mark.parametrize("results_csv", ["stale", "deleted", "corrupt"])
def test_report_results_and_compare_show_the_runs_whatever_results_csv_holds(tmp_path, capsys, results_csv):
    """A run killed after its rename, before the folder's results.csv was made again, leaves the
    table of the runs before it (here: repository profile, on labels since corrected) beside runs of
    the paper profile on the corrected labels, which alone the folder now shows."""
    folder = tmp_path / "outputs" / "toy"
    for profile, view in (("repository", True), ("paper", False)):
        earlier = {"label": [1, 0] * 3 + [0, 1]} if view else {}
        binding = {"pairs_digest": "earlier labels" if view else "corrected labels"}
        write_run(folder, "sift-nn", toy_table([9, 1, 8, 2, 7, 3, 6, 4]).assign(**earlier), profile, binding=binding)
        write_run(folder, "orb-nn", toy_table([5, 6, 4, 3, 7, 2, 1, 8]).assign(**earlier), profile, binding=binding)
        if view:
            scoring.refresh_view(folder)  # as the door that added the runs does
    stale = folder / "results.csv"
    assert set(pd.read_csv(stale)["profile"]) == {"repository"}
    if results_csv == "deleted":
        stale.unlink()
    elif results_csv == "corrupt":
        stale.write_text("sequence,method\n\x00garbage")
    capsys.readouterr()

    def profiles_shown(output: str) -> set[str]:  # the profile column of the table's rows
        return set(re.findall(r"^ *(?:sift|orb)-nn +(paper|repository) ", output, re.M))

    assert cli.main(["results", str(folder)]) == 0
    assert profiles_shown(capsys.readouterr().out) == {"paper"}
    assert cli.main(["compare", str(folder), "--resamples", "100"]) == 0
    shown = capsys.readouterr().out
    assert "paper" in shown and "repository" not in shown

    assert report.run_folders(parse("--outputs-root", str(tmp_path / "outputs"))) == [folder]
    assert report.run_folders(parse("--outputs-root", str(folder))) == [folder]
    index = page(tmp_path, folder)
    intervals = index.split("95% bootstrap intervals")[1]
    rows = re.findall(r"<tr>\s*<td>([^<]+)</td>\s*<td>([^<]*)</td>", intervals)
    assert rows == [("sift-nn", "paper"), ("orb-nn", "paper")]
    assert "paper profile" in index


@pytest.mark.reliability
def test_the_index_names_the_methods_its_view_leaves_out_and_the_collapsed_inlier_line(tmp_path, capsys):
    folder = tmp_path / "toy"
    # orb-nn's latest run scored other labels: the folder shows the later runs' pairs without it.
    write_run(
        folder,
        "orb-nn",
        toy_table([5, 6, 4, 3, 7, 2, 1, 8]),
        "repository",
        n_pairs=8,
        binding={"pairs_digest": "other"},
    )
    write_run(folder, "sift-nn", toy_table([9, 1, 8, 2, 7, 3, 6, 4], collapsed=True), "repository")
    write_run(folder, "xfeat-nn", toy_table([9, 1, 8, 2, 7, 3, 6, 4]), "repository")
    scoring.refresh_view(folder)
    assert cli.main(["results", str(folder)]) == 0
    said = capsys.readouterr().err.splitlines()
    left_out = [line.removeprefix("not in this table: ") for line in said if line.startswith("not in this table:")]
    warnings = [line.removeprefix("warning: ") for line in said if line.startswith("warning:")]
    assert len(left_out) == 1 and left_out[0].startswith("orb-nn: its latest run")
    assert len(warnings) == 1 and warnings[0].startswith("sift-nn: MR is set by false pair")

    index = " ".join(page(tmp_path, folder).split())
    assert f"not in this table: {left_out[0]}" in index
    assert f"warning: {warnings[0]}" in index
