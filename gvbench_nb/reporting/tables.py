"""Tables as text for a terminal or a README."""

from __future__ import annotations

from typing import Any


def markdown_table(frame: Any) -> str:
    """A pandas frame as a GitHub markdown table (floats to 3 decimals)."""
    header = "| " + " | ".join(map(str, frame.columns)) + " |"
    rule = "|" + "|".join("---" for _ in frame.columns) + "|"
    cell = lambda v: f"{v:.3f}" if isinstance(v, float) else str(v)
    rows = ["| " + " | ".join(cell(v) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join([header, rule, *rows])
