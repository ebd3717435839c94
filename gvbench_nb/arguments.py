"""What the commands' options share: argparse types that read a bounded whole number."""

from __future__ import annotations

import argparse


def whole_number_at_least(text: str, minimum: int, what: str) -> int:
    """``text`` as a whole number of at least ``minimum``; otherwise argparse's error, saying the
    value ``must be {what}``."""
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value
