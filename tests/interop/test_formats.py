"""The format registry: every registered format's module meets the entry-point contract, and the
command line's choices, options and dispatch come from the registry alone."""

from __future__ import annotations

import argparse
import inspect

import pytest

from rlu.data.formats import FORMATS, format_module, options_of
from rlu.types import RluError


@pytest.mark.parametrize("name", list(FORMATS))
def test_every_format_module_has_the_entry_points(name):
    fmt = FORMATS[name]
    module = format_module(name)
    export = inspect.signature(module.export)
    assert list(export.parameters)[:2] == ["ds", "out"]
    for keyword in ("overwrite", "note"):
        assert export.parameters[keyword].kind is inspect.Parameter.KEYWORD_ONLY
    imported = inspect.signature(module.import_dataset)
    assert list(imported.parameters)[:3] == ["src", "dest", "task_id"]
    for option in fmt.options:
        where = export if "export" in option.commands else imported
        assert option.dest in where.parameters, (name, option.flag)
    assert fmt.extra and fmt.packages and fmt.source


def _subparser(command):
    from rlu.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


@pytest.mark.parametrize("command", ["export", "import"])
def test_cli_choices_and_options_come_from_the_registry(command):
    parser = _subparser(command)
    fmt = next(a for a in parser._actions if "--format" in a.option_strings)
    assert fmt.choices == list(FORMATS)
    flags = {s for a in parser._actions for s in a.option_strings}
    theirs = {o.flag for f in FORMATS.values() for o in f.options if command in o.commands}
    others = {o.flag for f in FORMATS.values() for o in f.options} - theirs
    assert theirs <= flags and not (others & flags)


def test_an_option_of_another_format_is_refused():
    with pytest.raises(RluError, match="--minari-dir does not apply to rlu export --format d4rl"):
        options_of("d4rl", "export", {"minari_dir": "/tmp/x", "id": None})
    assert options_of("minari", "export", {"id": "a/b-v0"}) == {"id": "a/b-v0", "minari_dir": None}


def test_missing_extra_of_a_format_is_named():
    from rlu.cli import EXTRA_OF

    for f in FORMATS.values():
        for package in f.packages:
            assert EXTRA_OF[package] == f.extra
