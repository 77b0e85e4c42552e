"""Each training option is declared once, as a config dataclass field that carries its help text;
the command line is generated from those fields.

A field made with `option` is also a flag: ``--name-with-dashes`` (or ``flag=``), typed by the
field's annotation. ``X | None`` takes an X; ``list[X]`` / ``tuple[X, ...]`` is repeatable
(``action="append"``); a ``bool`` field that defaults to True is switched off by its flag (e.g.
``--no-amp``), one that defaults to False is switched on. A field without a default is a required
flag. Plain fields (no `option`) are settings of the library API only.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from dataclasses import MISSING, Field
from typing import Any

_KEY = "pair_vpr_ros.option"


def option(default: Any = MISSING, help: str = "", flag: str | None = None, **argparse_kw) -> Any:  # noqa: A002
    """A dataclass field that is also a flag. ``help`` may use ``%(default)s``; ``argparse_kw``
    go to ``add_argument`` (choices, metavar)."""
    meta = {_KEY: {"help": help, "flag": flag, **argparse_kw}}
    if isinstance(default, list):
        return dataclasses.field(default_factory=default.copy, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def redefault(cls: type, name: str, default: Any) -> Any:
    """The option ``name`` declared in ``cls`` with another default (one stage's own)."""
    return dataclasses.field(default=default, metadata=cls.__dataclass_fields__[name].metadata)


def _options(cls: type) -> list[tuple[Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if _KEY in f.metadata]


def _element(hint: Any) -> tuple[Any, bool]:
    """(argparse type, repeatable) of a field annotation."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):  # X | None
        return _element(args[0])
    if origin in (list, tuple):
        return args[0], True
    return hint, False


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """One flag for each `option` field of the dataclass ``cls``, in field order."""
    for f, hint in _options(cls):
        kw = dict(f.metadata[_KEY])
        flag = kw.pop("flag") or "--" + f.name.replace("_", "-")
        default = f.default_factory() if f.default_factory is not MISSING else f.default
        if hint is bool:
            action = "store_false" if default else "store_true"
            parser.add_argument(flag, dest=f.name, action=action, **kw)
            continue
        kind, repeatable = _element(hint)
        if default is MISSING:
            kw["required"] = True
        else:
            kw["default"] = list(default) if repeatable else default
        if repeatable:
            kw["action"] = "append"
        parser.add_argument(flag, dest=f.name, type=kind, **kw)


def config_from_args(cls: type, args: argparse.Namespace, **fixed: Any) -> Any:
    """The dataclass ``cls`` from parsed flags (``fixed`` sets fields that have no flag)."""
    values = {}
    for f, hint in _options(cls):
        value = getattr(args, f.name)
        if typing.get_origin(hint) is tuple and value is not None:
            value = tuple(value)
        values[f.name] = value
    return cls(**values, **fixed)
