"""What users read describes runs: ``--help``, every subcommand's help, outputs/README.md and
docs/usage.md name ``<output_dir>/runs/<id>/<method>/pairs.csv``, never the layout before runs, and
say one thing of an import under a name the folder already shows: it adds a run, which the folder shows."""

from __future__ import annotations

import argparse
import re

import pytest

from gvbench_nb import cli
from gvbench_nb.runner import config

OLD_LAYOUT = re.compile(r"(?<!runs/<id>/)(<output_dir>/<method>|finished <method>/pairs\.csv|<OUTPUT_DIR>/<method>)")
IMPORT_SHOWN = ("adds a run", "shows the import")


def helps(parser: argparse.ArgumentParser, name: str = "python -m gvbench_nb") -> dict[str, str]:
    """Every command's --help text, by its command line."""
    found = {name: parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, subparser in action.choices.items():
                found |= helps(subparser, f"{name} {sub}")
    return found


@pytest.mark.reliability
def test_every_help_and_the_outputs_readme_describe_runs():
    texts = helps(cli.build_parser())
    assert len(texts) > 10
    texts["outputs/README.md"] = (config.PROJECT_ROOT / "outputs" / "README.md").read_text(encoding="utf-8")
    texts["docs/usage.md"] = (config.PROJECT_ROOT / "docs" / "usage.md").read_text(encoding="utf-8")
    stale = {where: OLD_LAYOUT.findall(" ".join(text.split())) for where, text in texts.items()}
    assert {where: found for where, found in stale.items() if found} == {}
    for where in ("python -m gvbench_nb", "python -m gvbench_nb run", "outputs/README.md"):
        assert "runs/<id>/" in " ".join(texts[where].split()), where
    assert "runs/<id>/<method>/pairs.csv" in " ".join(texts["python -m gvbench_nb compare"].split())


@pytest.mark.reliability
def test_an_import_under_a_shown_name_is_said_one_way_everywhere():
    texts = {
        "import-scores --help": helps(cli.build_parser())["python -m gvbench_nb import-scores"],
        "docs/usage.md": (config.PROJECT_ROOT / "docs" / "usage.md").read_text(encoding="utf-8"),
        "outputs/README.md": (config.PROJECT_ROOT / "outputs" / "README.md").read_text(encoding="utf-8"),
    }
    for where, text in texts.items():
        flat = " ".join(text.split())
        assert all(words in flat for words in IMPORT_SHOWN), where
        assert "never replaces" not in flat and "it is refused (give another `--method`" not in flat, where
