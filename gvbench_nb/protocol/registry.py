"""One lookup for every named choice (methods, profiles, extractor and matcher types,
verifiers, pair builders, datasets, checkpoints...), with one error and one did-you-mean.

Types named in confs are ``"package.module:Class"`` references, imported only when built,
so listing or checking names never imports torch; a conf may also name its own class by
such a reference, which is how a matcher from outside the package is plugged in.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from gvbench_nb import GVBenchError

T = TypeVar("T")


class UnknownNameError(GVBenchError, KeyError):
    """A name that is not in its table."""

    def __str__(self) -> str:  # KeyError quotes its message; ours reads as a sentence
        return str(self.args[0])


def unknown_name_message(kind: str, name: object, known: Iterable[str], where: str = "") -> str:
    """``unknown matcher type 'lightglu' in <where>. Did you mean 'lightglue'? Known: ...``"""
    known = [str(k) for k in known]
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    place = f" in {where}" if where else ""
    return f"unknown {kind} {name!r}{place}.{hint} Known: {', '.join(known)}"


def lookup(
    kind: str,
    name: str,
    table: Mapping[str, T],
    where: str = "",
    also: Iterable[str] = (),
    error: type[Exception] = UnknownNameError,
) -> T:
    """``table[name]``, or ``error`` with the closest known name (``also``: further valid spellings)."""
    try:
        return table[name]
    except (KeyError, TypeError):
        raise error(unknown_name_message(kind, name, [*table, *also], where)) from None


def check_choice(
    kind: str, value: object, choices: Iterable[Any], where: str = "", error: type[Exception] = ValueError
) -> None:
    """Raise ``error`` unless ``value`` is one of ``choices`` (for option values, not table keys)."""
    choices = list(choices)
    if value not in choices:
        raise error(unknown_name_message(kind, value, [str(c) for c in choices], where))


def load_reference(reference: str) -> Any:
    """The object a ``"package.module:Attribute"`` reference names (imported now)."""
    module_name, _, attribute = reference.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"{reference!r} is not a 'package.module:Class' reference")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        raise ValueError(f"cannot import {module_name!r} for {reference!r}: {error}") from None
    try:
        return getattr(module, attribute)
    except AttributeError:
        raise ValueError(f"module {module_name!r} has no {attribute!r} (from {reference!r})") from None


def resolve_type(kind: str, type_name: str, types: Mapping[str, str], where: str = "") -> Any:
    """The class for a conf's ``type``: a registered short name or a ``module:Class`` reference."""
    reference = type_name if ":" in type_name else lookup(kind, type_name, types, where)
    return load_reference(reference)
