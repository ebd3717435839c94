"""One lookup for every named choice (methods, profiles, model types, verifiers, datasets,
checkpoints...), with one error and one did-you-mean. Models register by recipe ``type``; families
are imported at first build, so listing never imports torch; ``"package.module:Class"`` also works."""

from __future__ import annotations

import builtins
import difflib
import importlib
import pkgutil
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, TypeVar

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
    error: type[Exception] = UnknownNameError,
) -> T:
    """``table[name]``, or ``error`` with the closest known name."""
    try:
        return table[name]
    except (KeyError, TypeError):
        raise error(unknown_name_message(kind, name, list(table), where)) from None


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


class Model:
    """The contract of an extractor or a matcher: a subclass names the recipe ``type`` it
    implements, is built as ``Class(conf, device)`` with its recipe's conf, and is called
    (``features/base.py``, ``matching/base.py`` say on what)."""

    type: ClassVar[str]  # the recipe's ``type`` value naming this implementation
    types: ClassVar[dict[str, builtins.type[Model]]]  # the family's table: set by a family base

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "types" not in vars(cls) and "type" in vars(cls):
            cls.types[cls.type] = cls

    def __init__(self, conf: dict[str, Any], device: Any) -> None:
        self.conf, self.device = conf, device


def model_class(kind: str, family: builtins.type[Model], package: str, conf: dict[str, Any]) -> Any:
    """The class for a conf's ``type``: one of ``package``'s models, or a ``module:Class`` reference."""
    type_name = conf["type"]
    if ":" in type_name:
        return load_reference(type_name)
    if type_name not in family.types:  # the family's files register their classes when imported
        for module in pkgutil.iter_modules(importlib.import_module(package).__path__):
            importlib.import_module(f"{package}.{module.name}")
    return lookup(kind, type_name, family.types, f"{kind.split()[0]} conf {conf.get('name', '?')!r}")
