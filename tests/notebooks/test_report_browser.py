"""The HTML report as a page in a real browser: every image loads (the PR curves among them),
every link resolves, the tables name their runs' profiles, the notebook pages show no code, and
no page logs an error.

A small report is built from the embedded ``sample`` route (two cheap methods, the first
pairs only), then headless Chromium (the system's, driven by playwright) opens
``index.html`` over file:// and every notebook page it links to. Skips, naming the install
commands, when Chromium or playwright is missing.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from urllib.parse import unquote, urldefrag, urljoin, urlparse

import pytest

from gvbench_nb.reporting import report

PROJECT_ROOT = Path(__file__).resolve().parents[2]
METHODS = "sift-nn,orb-nn"
PROFILE = "repository"
LIMIT = "24"  # 24 pairs, 9 of them true: enough for every analysis notebook, seconds to run


def pinned(package: str) -> str:
    """The version environment.txt pins for a package ('' when it pins none)."""
    found = re.search(rf"^{re.escape(package)}==(\S+)", (PROJECT_ROOT / "environment.txt").read_text(), re.M)
    return found.group(1) if found else ""


@pytest.fixture(scope="module")
def chromium():
    """The system Chromium's path and playwright's driver; skips naming what to install."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    missing = ([] if path else ["Chromium (`apt-get install chromium`)"]) + (
        [] if sync_playwright else [f"playwright (`pip install playwright=={pinned('playwright')}`)"]
    )
    if missing:
        pytest.skip(f"the browser test needs {' and '.join(missing)}")
    return path, sync_playwright


@pytest.fixture(scope="module")
def report_index(chromium, tmp_path_factory) -> Path:
    """``index.html`` of a report over a small sample run (built only once the browser is found)."""
    from gvbench_nb import cli

    root = tmp_path_factory.mktemp("report_browser")
    params = root / "sample.yaml"
    params.write_text(
        "sequence: sample\npairs_builder: sample\nbuilder_options: {}\n"
        f"image_root: {root / 'data'}\npairs: {root / 'data' / 'pairs.txt'}\n"
        f"methods: [{METHODS}]\nprofile: {PROFILE}\noutput_dir: {root / 'outputs' / 'sample'}\nseed: 0\n"
    )
    # One shard and its merge write what a plain run writes, without the run's own notebooks,
    # which the report does not read.
    base = ["run", str(params), "--methods", METHODS, "--limit", LIMIT]
    assert cli.main([*base, "--shard", "0/1"]) == 0
    assert cli.main([*base, "--merge"]) == 0
    assert cli.main(["report", str(root / "outputs" / "sample"), "--output-dir", str(root / "report")]) == 0
    return root / "report" / "index.html"


# Lines a page must not hold: notebook bookkeeping printed into the report, and numbers unrounded.
STRAY = re.compile(r"\d+ results of \d+ sequence|paper's table: \d+ rows|\d\.\d{5,}")
MAX_PAGE_BYTES = 2_000_000


def check_page(browser, url: str) -> tuple[object, list[str]]:
    """Open a page; assert it is under 2 MB, its images loaded, its anchors exist, it holds no
    stray printout and nothing logged an error. Returns the page (still open) and the local
    files its links point to."""
    size = Path(unquote(urlparse(url).path)).stat().st_size
    assert size < MAX_PAGE_BYTES, f"{url}: {size:,} bytes"
    page = browser.new_page()
    errors: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("requestfailed", lambda request: errors.append(f"{request.url}: {request.failure}"))
    page.goto(url, wait_until="load")
    images = page.evaluate(
        "[...document.images].map(i => [i.getAttribute('src').slice(0, 80), i.complete && i.naturalWidth > 0])"
    )
    assert [src for src, loaded in images if not loaded] == [], f"{url}: images that did not load"
    targets = []
    for href in page.evaluate("[...document.querySelectorAll('a[href]')].map(a => a.getAttribute('href'))"):
        absolute, fragment = urldefrag(urljoin(url, href))
        if urlparse(absolute).scheme != "file":
            continue  # an outside link cannot be checked offline
        path = Path(unquote(urlparse(absolute).path))
        assert path.is_file(), f"{url}: link {href!r} points to a missing file"
        if absolute == urldefrag(url)[0] and fragment:
            name = unquote(fragment)
            assert page.evaluate("n => !!(document.getElementById(n) || document.getElementsByName(n).length)", name), (
                f"{url}: anchor {href!r} names no element of the page"
            )
        elif path.suffix == ".html":
            targets.append(path)
    assert errors == [], f"{url}: console errors"
    text = page.evaluate("document.body.innerText")
    assert not STRAY.search(text), f"{url}: stray line {STRAY.search(text).group(0)!r}"
    return page, targets


@pytest.mark.slow
def test_report_page_loads_its_images_and_links_and_names_profiles(chromium, report_index):
    path, sync_playwright = chromium
    with sync_playwright() as driver:
        # The system Chromium: playwright's own browser download is not needed.
        browser = driver.chromium.launch(executable_path=path, headless=True)
        try:
            check_report(browser, report_index)
        finally:
            browser.close()


def check_report(browser, index: Path) -> None:
    page, linked = check_page(browser, index.as_uri())
    sources = page.evaluate("[...document.images].map(i => i.getAttribute('src'))")
    assert "max_recall_radar.png" in sources and "pr_curves_sample.png" in sources
    assert {f"sample/{name.format(sequence='sample')}" for name in report.KEY_FIGURES} <= set(sources)
    assert page.locator(".error").count() == 0, "a notebook failed: " + page.locator(".error").first.inner_text()
    # Every table has a 'profile' header and names the run's profile on each of its data rows.
    tables = page.evaluate("""[...document.querySelectorAll('table')].map(t => ({
        headers: [...t.querySelectorAll('thead th')].map(c => c.innerText.trim()),
        rows: [...t.querySelectorAll('tbody tr')].map(r => [...r.cells].map(c => c.innerText.trim()))}))""")
    assert len(tables) == 2  # the results table and the sample's bootstrap intervals
    for table in tables:
        assert "profile" in table["headers"], table["headers"]
        assert table["rows"] and all(PROFILE in row for row in table["rows"]), table["rows"]
    # Each row of the results table says how many pairs it has, and that --limit cut them.
    assert "pairs" in tables[0]["headers"] and all(f"{LIMIT} (--limit)" in row for row in tables[0]["rows"])
    page.close()
    # The notebooks it links to: the one across sequences and the sample's own.
    assert len(linked) == 1 + len(report.PER_SEQUENCE_NOTEBOOKS)
    for target in linked:
        notebook_page, _ = check_page(browser, target.as_uri())
        # Outputs only: no code cell's source is on the page.
        assert notebook_page.locator(".jp-InputArea-editor").count() == 0, target
        assert notebook_page.locator(".jp-OutputArea").count() > 0, target
        # Every page leads back to the index; no table shows pandas' index column.
        back = notebook_page.evaluate("[...document.querySelectorAll('a[href]')].map(a => a.href)")
        assert index.as_uri() in back, f"{target}: no link back to the index"
        row_numbers = "[...document.querySelectorAll('tbody tr:first-child > th:first-child')].map(c => c.innerText)"
        assert "0" not in [text.strip() for text in notebook_page.evaluate(row_numbers)], f"{target}: row numbers"
        notebook_page.close()
