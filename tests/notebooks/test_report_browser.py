"""The HTML report of a small sample run, with a method imported from a table of scores, in headless
Chromium: every image loads, every link resolves, the tables name their runs' profiles, the notebook
pages show no code, no page logs an error; and the pages read as one paper: no warning text, no
`nan` cell, the imported method labelled '(imported)' wherever it is named, AP and MR in % under
worded headers, no synthetic route in an Average, the published tables in one sequence order."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from urllib.parse import unquote, urldefrag, urljoin, urlparse

import pandas as pd
import pytest
import yaml

from gvbench_nb.reporting import execute, report
from gvbench_nb.runner import method_outputs
from gvbench_nb.studies import condition_sweep

PROJECT_ROOT = Path(__file__).resolve().parents[2]
METHODS = "sift-nn,orb-nn"
PROFILE = "repository"
LIMIT = "24"  # pairs of the second sequence: enough for every analysis notebook, seconds to run
IMPORTED = "my-tool"  # scores imported from a table (no inlier counts, no seconds) into the sample's folder


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
    # A second sequence of the same images, built by retrieval: the transfer matrix has two rows
    # and the build page its input.
    retrieval = root / "sample_retrieval.yaml"
    built = yaml.safe_load((PROJECT_ROOT / "params" / "sample_retrieval.yaml").read_text())
    built.update(image_root=str(root / "data"), pairs=str(root / "retrieval_pairs.txt"), profile=PROFILE)
    built.update(output_dir=str(root / "outputs" / "sample_retrieval"), methods=METHODS.split(","))
    retrieval.write_text(yaml.safe_dump(built))
    # One shard and its merge write what a plain run writes, without the run's own notebooks,
    # which the report does not read.
    # The sample whole (240 pairs): the verifiers' place-disjoint split needs its 30 queries.
    for path, limit in ((params, []), (retrieval, ["--limit", LIMIT])):
        base = ["run", str(path), "--methods", METHODS, *limit]
        assert cli.main([*base, "--shard", "0/1"]) == 0
        assert cli.main([*base, "--merge"]) == 0
    # A method imported beside them from a table of scores alone (sift-nn's scores).
    sample = root / "outputs" / "sample"
    scores = root / "scores.csv"
    table = pd.read_csv(method_outputs.method_dir(sample, "sift-nn") / "pairs.csv")
    table[["query", "reference", "label", "score"]].to_csv(scores, index=False)
    imported = ["import-scores", str(scores), "--sequence", "sample", "--method", IMPORTED]
    assert cli.main([*imported, "--output-dir", str(sample)]) == 0
    # The verifiers compared on the sample's sift-nn matches (the verifier pages' input), and a
    # tiny condition sweep beside the runs (the sweep page's).
    verifiers = {"params_file": None, "results_dir": str(sample), "method": "sift-nn"}
    target = sample / report.VERIFIERS_FOLDER
    execute.execute_notebook(
        "analysis_verifiers.ipynb", target / "verifiers.ipynb", {**verifiers, "output_dir": str(target)}
    )
    condition_sweep.run_sweep(
        root / "outputs" / "sweep", ["orb-nn"], conditions=["illumination"], strengths=[1.0], n_frames=8,
        profile=PROFILE, image_size=(160, 120), threads=1, progress=False,
    )  # fmt: skip
    assert cli.main(["report", "--outputs-root", str(root / "outputs"), "--output-dir", str(root / "report")]) == 0
    return root / "report" / "index.html"


# Lines a page must not hold: notebook bookkeeping printed into the report, numbers unrounded, and
# warnings or tracebacks a cell printed.
STRAY = re.compile(r"\d+ results of \d+ sequence|paper's table: \d+ rows|\d\.\d{5,}|Warning\b|Traceback")
SYNTHETIC = {"sample", "sample_retrieval"}  # both sequences are the rendered route's
MAX_PAGE_BYTES = 2_000_000


def check_page(browser, url: str) -> tuple[object, list[str]]:
    """Open a page and check its size, images, anchors, text and console; return it (open) and the
    local pages it links to."""
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
    check_reads_as_one_paper(page, url, text)
    return page, targets


def check_reads_as_one_paper(page, url: str, text: str) -> None:
    """No `nan` cell; the imported method labelled '(imported)' wherever named; headers in words, AP
    and MR in %; no synthetic sequence in an Average; the published tables in one sequence order."""
    cells = page.evaluate("[...document.querySelectorAll('td, th')].map(c => c.innerText.trim().toLowerCase())")
    assert not {"nan", "none"} & set(cells), f"{url}: a nan cell"
    if IMPORTED in text:
        assert f"{IMPORTED} (imported)" in text, f"{url}: {IMPORTED} named without '(imported)'"
    assert f"{IMPORTED} ({IMPORTED}" not in text and "imported profile" not in text, url
    assert "profile profile" not in text and f"[{PROFILE}]" not in text, f"{url}: a profile written another way"
    headers = page.evaluate("""[...document.querySelectorAll('table')].map(t =>
        [...t.querySelectorAll('thead th')].map(c => c.innerText.trim()))""")
    for header in headers:
        raw = [h for h in header if ("_" in h and h not in SYNTHETIC) or h.lower() in ("ap", "max_recall", "mr")]
        assert raw == [], f"{url}: raw column names in a header {header}"
        assert all("(%)" in h for h in header if re.search(r"\b(AP|MR)\b", h)), f"{url}: AP or MR not in % {header}"
        if "Average" in header:
            assert not SYNTHETIC & set(header), f"{url}: a synthetic sequence averaged {header}"
    # A header names its sequences once a metric: each run of them in the paper's order.
    published = [list(dict.fromkeys(h for h in header if h in PAPER_SEQUENCES)) for header in headers]
    orders = [order for order in published if len(order) > 1]
    assert all(order == [s for s in PAPER_SEQUENCES if s in order] for order in orders), f"{url}: {orders}"


# The paper's sequence order, which every published table and radar follows.
PAPER_SEQUENCES = ["day", "night", "season", "weather", "nordland", "uacampus"]


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
    # The paper's figures (Fig. 1 of the published values alone, Fig. 8's grouping) and deployment's.
    assert set(report.PAPER_FIGURES.values()) | {"threshold_transfer.png"} <= set(sources)
    assert page.locator(".error").count() == 0, "a notebook failed: " + page.locator(".error").first.inner_text()
    check_paper_tables(page)
    # Every table of runs has a 'profile' header and names the run's profile on each of its data rows.
    tables = page.evaluate("""[...document.querySelectorAll('table:not(.table-ii)')].map(t => ({
        headers: [...t.querySelectorAll('thead th')].map(c => c.innerText.trim()),
        rows: [...t.querySelectorAll('tbody tr')].map(r => [...r.cells].map(c => c.innerText.trim()))}))""")
    # the results table, Table III of the synthetic routes, the loop closures and each sequence's
    # bootstrap intervals
    assert len(tables) == 5
    for table in tables:
        assert "profile" in table["headers"], table["headers"]
        assert table["rows"] and all(PROFILE in row or "imported" in row for row in table["rows"]), table["rows"]
    # Each row of the results table says how many pairs it has, and whether --limit cut them.
    rows = tables[0]["rows"]
    assert "pairs" in tables[0]["headers"] and all(f"{LIMIT} (--limit)" in row or "240 (all)" in row for row in rows)
    assert any(f"{LIMIT} (--limit)" in row for row in rows) and any("240 (all)" in row for row in rows)
    page.close()
    # The notebooks it links to: those across sequences, each sequence's own and the studies'
    # pages whose inputs exist: the verifiers and Doppelgangers where the sample's were compared,
    # the build of the retrieval-built sequence, the sweep.
    names = [target.name for target in linked]
    assert len(linked) == 1 + len(report.PAPER_NOTEBOOKS) + 2 * len(report.PER_SEQUENCE_NOTEBOOKS) + 2 + 1 + 1
    for name in ("analysis_verifiers", "analysis_doppelgangers", "00_build_sequence", "analysis_condition_sweep"):
        assert f"{name}.html" in names, names
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


def check_paper_tables(page) -> None:
    """Table II shows the counted and the paper's text values, each labelled; Table III holds no
    recorded sequence here, the synthetic routes' table no Average, and marks the 1st (bold), 2nd
    (underlined) and 3rd (italic) of a column."""
    summary = page.evaluate("""[...document.querySelectorAll('table.table-ii tbody tr')]
        .map(r => [...r.cells].map(c => c.innerText.trim()))""")
    sources = {row[1] for row in summary}
    assert {"counted from the run", "paper (text)"} <= sources, sources
    assert ["nordland", "paper (text)", "-", "seasonal", "-", "1,415", "-", "28,300", "-"] in summary
    assert page.locator("#table-iii").locator("xpath=following-sibling::*[1]").inner_text() == (
        "No recorded sequence ran."
    )
    table = page.locator("#table-iii-synthetic").locator("xpath=following-sibling::table[1]")
    header = table.locator("thead").inner_text()
    assert "Average" not in header and "sample" in header and "sample_retrieval" in header
    styles = table.evaluate("""t => [...t.querySelectorAll('tbody td')].map(c => {
        const s = getComputedStyle(c); return [c.innerText.trim(), s.fontWeight, s.textDecorationLine, s.fontStyle]})""")
    # Two methods on each column: a 1st (bold) and a 2nd (underlined) where they differ.
    assert any(weight == "700" for _, weight, _, _ in styles)
    assert any(line == "underline" for _, _, line, _ in styles)
