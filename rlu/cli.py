"""The ``rlu`` command: parsing and printing only; the logic lives in the library.

Every module in ``rlu/commands/`` contributes subcommands through ``register(subparsers)``; such
modules import only the standard library at the top and the library inside their handlers, so
``rlu list`` stays a numpy-only command.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from rlu.types import RluError


def build_parser() -> argparse.ArgumentParser:
    import rlu.commands

    parser = argparse.ArgumentParser(
        prog="rlu", description="RL Unplugged: datasets, environments, baselines, evaluation."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(rlu.commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"rlu.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except RluError as e:
        print(f"rlu: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rlu: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
