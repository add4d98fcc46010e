"""The command line's options derived from config dataclasses: one option per field, typed,
range-checked and helped by the field (:func:`add_options`), the value back from the parsed
options (:func:`from_args`), and what the user typed (:func:`typed_dests`, :func:`flat_values`
for a config file's values under the same names). Only the commands use these; the configs
themselves (``rlu.training.config.RunSettings``, the agents' configs) live below them.

A field's metadata may hold ``min`` / ``max`` / ``gt`` / ``lt`` / ``choices`` (checked by the
parser and in files), ``flag`` (the option's name when it is not ``--field-name``),
``cli_default`` (the command line's default where it differs on purpose from the library's:
``--device auto``), ``metavar``.
Help text is the field's docstring (the string literal under it), read from the source once.

Standard library only.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import textwrap
import typing
from typing import Any

from rlu.training.config import scalar_hint
from rlu.types import RluError


# --- field docs -----------------------------------------------------------------------------
@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of dataclass ``cls`` (and of its bases), one line."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def checked(kind: Any, meta: dict[str, Any], flag: str) -> Any:
    """An argparse ``type`` parsing ``kind`` (int or float) within ``meta``'s bounds (``min`` /
    ``max`` / ``gt`` / ``lt``, as :func:`rlu.files.bounds` writes them)."""
    import math

    lo, hi, gt, lt = meta.get("min"), meta.get("max"), meta.get("gt"), meta.get("lt")

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            name = "an integer" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"{text!r} is not {name}") from None
        if (
            not math.isfinite(value)
            or (lo is not None and value < lo)
            or (hi is not None and value > hi)
            or (gt is not None and value <= gt)
            or (lt is not None and value >= lt)
        ):
            want = " and ".join(
                s
                for s in (
                    f"> {gt}" if gt is not None else "",
                    f">= {lo}" if lo is not None else "",
                    f"< {lt}" if lt is not None else "",
                    f"<= {hi}" if hi is not None else "",
                )
                if s
            )
            raise argparse.ArgumentTypeError(
                f"{value} is out of range; give a {'finite ' if kind is float else ''}value "
                f"{want}".rstrip()
            )
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its own messages
    return parse


def add_options(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    only: tuple[str, ...] | None = None,
    skip: tuple[str, ...] = (),
    dest_prefix: str = "",
    flag_prefix: str = "--",
    require: bool = True,
) -> None:
    """One option per field of dataclass ``cls`` (nested dataclasses: their fields, flattened),
    typed, range-checked and helped by the field; ``only`` / ``skip`` choose fields. A field
    without a default is a required option (``require=False``: the command checks it, e.g.
    after reading a config file); a tuple field takes one or more values."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        if (only is not None and f.name not in only) or f.name in skip:
            continue
        hint, _ = scalar_hint(hints[f.name])
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            add_options(parser, hint, dest_prefix=f"{dest_prefix}{f.name}.")
            continue
        meta = dict(f.metadata)
        flag = meta.get("flag", flag_prefix + f.name.replace("_", "-"))
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        default = f.default if f.default is not dataclasses.MISSING else None
        default = meta.get("cli_default", default)
        doc = docs.get(f.name, "")
        kwargs: dict[str, Any] = {"dest": dest_prefix + f.name}
        if required and require:
            kwargs["required"] = True
        elif required:
            kwargs["default"] = None
        else:
            kwargs["default"] = list(default) if isinstance(default, tuple) else default
        item = hint
        if typing.get_origin(hint) is tuple:
            item = typing.get_args(hint)[0]
            kwargs["nargs"] = "+"
        if item is bool:
            kwargs["action"] = "store_true"
            kwargs["help"] = doc
        else:
            if item in (int, float):
                kwargs["type"] = checked(item, meta, flag)
            if "choices" in meta:
                kwargs["choices"] = list(meta["choices"])
            if "metavar" in meta:
                kwargs["metavar"] = meta["metavar"]
            shown = ""
            if required and not require:
                doc += " (required, on the command line or in --config)"
            if not required and default is not None and "(default" not in doc:
                value = " ".join(map(str, default)) if isinstance(default, tuple) else default
                shown = f" (default: {value})"
            kwargs["help"] = (doc + shown).replace("%", "%%")
        parser.add_argument(flag, **kwargs)


def from_args(cls: type, args: argparse.Namespace, dest_prefix: str = "", **given: Any) -> Any:
    """The ``cls`` value of the options :func:`add_options` made (``given`` fills or overrides
    fields the command sets itself)."""
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    ns = vars(args)
    for f in dataclasses.fields(cls):
        if f.name in given:
            values[f.name] = given[f.name]
            continue
        hint, _ = scalar_hint(hints[f.name])
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            if any(k.startswith(f"{dest_prefix}{f.name}.") for k in ns):
                values[f.name] = from_args(hint, args, f"{dest_prefix}{f.name}.")
            continue
        if dest_prefix + f.name in ns:
            value = ns[dest_prefix + f.name]
            if typing.get_origin(hint) is tuple and isinstance(value, list):
                value = tuple(value)
            values[f.name] = value
    return cls(**values)


def typed_dests(parser: argparse.ArgumentParser, argv: list[str]) -> set[str]:
    """The ``dest`` of every option of ``parser`` that ``argv`` names (what the user typed; the
    parser takes no abbreviations, so a typed option is one of its full names)."""
    tokens = {t.split("=", 1)[0] for t in argv if t.startswith("--")}
    return {a.dest for a in parser._actions if tokens & set(a.option_strings)}


def flat_values(cls: type, data: dict[str, Any], dest_prefix: str = "") -> dict[str, Any]:
    """A (partial) nested config dict as the option dests :func:`add_options` gives the same
    fields (a nested dataclass's fields under ``dest_prefix + name + "."``)."""
    hints = typing.get_type_hints(cls)
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        hint, _ = scalar_hint(hints[f.name])
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            out.update(flat_values(hint, data[f.name], f"{dest_prefix}{f.name}."))
        else:
            value = data[f.name]
            out[dest_prefix + f.name] = list(value) if isinstance(value, tuple) else value
    return out


YAML_BOOLEANS = {
    **dict.fromkeys(("true", "True", "TRUE", "yes", "Yes", "YES", "on", "On", "ON"), True),
    **dict.fromkeys(("false", "False", "FALSE", "no", "No", "NO", "off", "Off", "OFF"), False),
}
"""The words a YAML config file's reader (PyYAML's safe loader, YAML 1.1) reads as booleans; an
override on the command line reads them the same way (``recurrent=true``)."""


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["learning_rate=3e-4", "hidden=(256, 256)", "atari.batch_size=64", "recurrent=true"]``
    -> typed values: Python literals, YAML's booleans (:data:`YAML_BOOLEANS`, as a config file
    reads them); other bare words stay strings. The agent config checks each against its field
    (``recurrent=maybe`` or ``recurrent=1``: refused, "expected true or false")."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise RluError(f"override {item!r}; write it as field=value, e.g. learning_rate=3e-4")
        text = text.strip()
        if text in YAML_BOOLEANS:
            out[key.strip()] = YAML_BOOLEANS[text]
            continue
        try:
            out[key.strip()] = ast.literal_eval(text)
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            out[key.strip()] = text
    return out
