"""What the commands' options and the params share: argparse types that read a bounded whole number,
and the did-you-mean of unknown keys."""

from __future__ import annotations

import argparse
import difflib
from typing import Any


def is_whole_number(value: Any) -> bool:
    """An int given in a params file or from code (YAML's ``yes`` is a bool, not 1)."""
    return isinstance(value, int) and not isinstance(value, bool)


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


def unknown_keys_hint(unknown: list[str], valid: list[str]) -> str:
    """``'limt' (did you mean 'limit'?), 'x'``: each unknown key with its closest valid one."""
    hints = []
    for key in unknown:
        close = difflib.get_close_matches(key, valid, n=1)
        hints.append(f"{key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return ", ".join(hints)


class SuggestingParser(argparse.ArgumentParser):
    """argparse's parser, with a did-you-mean for a mistyped command or choice (``rn`` -> ``run``).
    Its sub-command parsers are of this class too (argparse makes them of their parent's)."""

    def _check_value(self, action: argparse.Action, value: object) -> None:
        choices = action.choices
        if choices is not None and value not in choices:
            close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1)
            if close:
                known = ", ".join(map(str, choices))
                raise argparse.ArgumentError(
                    action, f"invalid choice: {value!r}; did you mean {close[0]!r}? (choose from {known})"
                )
        super()._check_value(action, value)
