"""``explore`` in headless Chromium: JupyterLab opens the working copy (unmodified, no pop-up), Run All
draws the controls, every pick and method redraws every view, and the tracked notebooks stay untouched."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from test_report_browser import chromium  # noqa: F401  (the fixture: Chromium's path and playwright)

from gvbench_nb import explore_lab
from gvbench_nb.runner import config, method_outputs, method_runs, sequence_build
from gvbench_nb.studies import explore_pairs as explore

PROJECT_ROOT = Path(__file__).resolve().parents[2]
METHODS = ["sift-nn", "orb-nn"]
TIMEOUT_MS = 60_000


@pytest.fixture(scope="module")
def run_folder(chromium, tmp_path_factory) -> Path:  # noqa: F811
    """A finished run's folder, 8 frames of 240x180 (built only once the browser is found)."""
    root = tmp_path_factory.mktemp("explore_browser")
    (root / "tiny.yaml").write_text(
        "sequence: tiny\npairs_builder: sample\nbuilder_options: {n_frames: 8, image_size: [240, 180]}\n"
        f"image_root: {root / 'data'}\npairs: {root / 'data' / 'pairs.txt'}\nmethods: {METHODS}\n"
        f"profile: repository\noutput_dir: {root / 'outputs' / 'tiny'}\nseed: 0\n"
    )
    loaded = config.load_params(root / "tiny.yaml") | {"device": "cpu"}
    sequence = sequence_build.prepare_sequence(loaded)
    for method in METHODS:  # as a notebook on its own runs it: a run of its own, with the params it ran on
        method_runs.run_method_of_params(loaded, sequence, method, progress=False)
    return Path(loaded["output_dir"])


@pytest.fixture
def lab(run_folder, tmp_path):
    """``explore`` serving the run on a free port; yields its printed URL, then stops it."""
    port = explore_lab.free_port(18888)
    home = tmp_path / "jupyter"  # JupyterLab's settings and workspaces: none of the user's
    environment = {
        **os.environ,
        "JUPYTER_CONFIG_DIR": str(home / "config"),
        "JUPYTER_RUNTIME_DIR": str(home / "runtime"),
        "JUPYTERLAB_SETTINGS_DIR": str(home / "settings"),
        "JUPYTERLAB_WORKSPACES_DIR": str(home / "workspaces"),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(PROJECT_ROOT), os.environ.get("PYTHONPATH")])),
    }
    server = subprocess.Popen(
        [sys.executable, "-m", "gvbench_nb", "explore", str(run_folder), "--no-browser", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=environment,
        cwd=tmp_path,
    )
    assert server.stdout is not None
    printed = [server.stdout.readline(), server.stdout.readline()]
    found = re.search(r"(http://127\.0\.0\.1:\d+/lab/tree/explore_pairs\.ipynb\?token=\w+)", printed[1])
    assert found, printed
    url = found.group(1)
    deadline = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(url.replace("/lab/tree/explore_pairs.ipynb", "/api/status"), timeout=2)
            break
        except OSError:
            assert server.poll() is None and time.monotonic() < deadline, "JupyterLab did not start"
            time.sleep(0.5)
    try:
        yield url
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()


def sources_status() -> str:
    return subprocess.run(
        ["git", "status", "--porcelain", "notebooks/"], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True
    ).stdout


def sources_bytes() -> dict[str, bytes]:
    """The tracked explore notebook and its twin, byte for byte (a checkout's own edits aside)."""
    return {
        name: (PROJECT_ROOT / "notebooks" / name).read_bytes() for name in ("explore_pairs.ipynb", "explore_pairs.py")
    }


def expected_status(index: int, pick: str, method: str) -> str:
    return f"pair {index}: pick {pick}, pick_method {method}, pick_rank 1; methods {', '.join(METHODS)}"


def check_views(page, index: int) -> None:
    """Every view shows pair ``index``: the table names it, each figure is a loaded image."""
    table = page.locator(".gvbench-view-table table")
    assert table.count() == 1
    # The table fits its cell (a wider one would scroll inside it, not overflow the notebook).
    area, cell = page.locator(".gvbench-view-table").bounding_box(), page.locator(".jp-Notebook").bounding_box()
    assert area and cell and area["x"] + area["width"] <= cell["x"] + cell["width"], (area, cell)
    cells = table.locator("tbody tr").evaluate_all("rows => rows.map(r => [...r.cells].map(c => c.innerText.trim()))")
    assert [row[0] for row in cells] == METHODS and {row[1] for row in cells} == {str(index)}, cells
    for view in ("matches", "scores"):
        images = page.locator(f".gvbench-view-{view} img")
        assert images.count() == 1, view
        assert images.evaluate("i => i.complete && i.naturalWidth > 0"), view


@pytest.mark.slow
def test_explore_in_jupyterlab_redraws_every_view_and_leaves_the_sources_clean(
    chromium,  # noqa: F811
    run_folder,
    lab,
    tmp_path,
):
    import pandas as pd

    path, sync_playwright = chromium
    before, before_bytes = sources_status(), sources_bytes()
    tables = {m: pd.read_csv(method_outputs.method_dir(run_folder, m) / "pairs.csv") for m in METHODS}
    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=path, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.set_default_timeout(TIMEOUT_MS)
            page.goto(lab)
            page.locator(".jp-Notebook").wait_for()
            # The kernel started (Run All before that asks which kernel to start).
            page.locator(".jp-StatusBar-Widget", has_text="Python 3 (ipykernel) | Idle").wait_for()
            # Opened as it was written: not marked modified before any edit, and no pop-up (the
            # news question JupyterLab asks on a first start).
            page.wait_for_timeout(1500)
            tab = page.locator(".lm-DockPanel-tabBar .lm-TabBar-tab", has_text="explore_pairs.ipynb")
            assert "jp-mod-dirty" not in (tab.get_attribute("class") or ""), "the tab is marked modified"
            assert page.locator(".Toastify__toast").all_inner_texts() == []
            page.get_by_role("menuitem", name="Run", exact=True).click()
            page.get_by_role("menuitem", name="Run All Cells", exact=True).click()
            status = page.locator(".gvbench-status")
            first = explore.choose_pair(tables, "false_positive", 0, METHODS[0], 1)
            status.get_by_text(expected_status(first, "false_positive", METHODS[0]), exact=True).wait_for()
            check_views(page, first)
            for pick in explore.PICKS:
                for method in METHODS:
                    page.locator(".gvbench-pick-method select").select_option(method)
                    page.locator(".gvbench-pick select").select_option(pick)
                    index = explore.choose_pair(
                        tables, pick, int(page.locator(".gvbench-pair-index input").input_value()), method, 1
                    )
                    status.get_by_text(expected_status(index, pick, method), exact=True).wait_for()
                    check_views(page, index)
                    assert page.locator(".gvbench-pair-index input").input_value() == str(index)
                    if pick == "false_negative":
                        page.screenshot(path=str(tmp_path / f"explore_{pick}_{method}.png"), full_page=True)
            # An index out of range is said and kept, not clamped; no figure stays under the message.
            box = page.locator(".gvbench-pair-index input")
            box.fill("9999")
            box.press("Enter")
            status.get_by_text(re.compile(r"0 to \d+, got 9999")).wait_for()
            assert box.input_value() == "9999" and page.locator(".gvbench-view-matches img").count() == 0
            # Every control's label is whole (not cut to 'pick_met...').
            for label in page.locator(".widget-label").all():
                assert label.evaluate("l => l.scrollWidth <= l.clientWidth"), label.inner_text()
            box.evaluate("b => b.blur()")  # a widget's text box keeps its keys from JupyterLab's shortcuts
            page.keyboard.press("Control+s")
            page.wait_for_timeout(2000)
        except Exception:
            page.screenshot(path=str(tmp_path / "failure.png"), full_page=True)  # what the page showed
            raise
        finally:
            browser.close()
    # Saving wrote the outputs into the working copy, and nothing into the tracked notebooks.
    assert "image/png" in (run_folder / "explore" / "explore_pairs.ipynb").read_text()
    # Every view replaced the last one's files: the folder holds the copy and one pair's figures.
    kept = {p.name for p in (run_folder / "explore").iterdir() if p.name != ".ipynb_checkpoints"}
    assert kept == {"explore_pairs.ipynb", *explore.FIGURE_FILES.values()}, kept
    assert sources_status() == before, sources_status()  # empty on a clean checkout
    assert sources_bytes() == before_bytes
