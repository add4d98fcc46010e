"""The ``rlu`` command: parsing and printing only; the logic lives in the library.

Every module in ``rlu/commands/`` contributes subcommands through ``register(subparsers)``
(``_name`` modules are helpers of the others, with no command of their own); such modules import
only the standard library at the top and the library inside their handlers, so ``rlu list``
stays a numpy-only command.

Bad input never ends in a traceback: the library raises :class:`~rlu.types.RluError` (the message
names the file, the field and the fix), and a file the system refuses (permissions, a full disk)
is an ``OSError``; both print one line. A reader that goes away (``rlu list | head -1``) ends the
command quietly. Exit codes are ``EXIT_CODES``.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import os
import pkgutil
import re
import sys
from collections.abc import Sequence
from typing import Any

from rlu.data.formats import extras_of_packages
from rlu.domains import DOMAINS
from rlu.types import RluError

EXIT_CODES = {
    0: "success",
    1: "rlu validate found problems",
    2: "bad input or usage (the message says what and how to fix it)",
    130: "interrupted (Ctrl-C)",
    141: "the output pipe was closed by its reader (128 + SIGPIPE, as a shell reports it)",
}


class Parser(argparse.ArgumentParser):
    """argparse's parser that says "did you mean" for a mistyped subcommand or option: every
    parser of the ``rlu`` command is one (subcommands' parsers take their parent's class)."""

    def parse_known_args(  # type: ignore[override]  # one signature for argparse's overloads
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> tuple[Any, list[str]]:
        namespace, extras = super().parse_known_args(args, namespace)
        leaf = not any(isinstance(a, argparse._SubParsersAction) for a in self._actions)
        if extras and leaf:  # the command's own parser: the options it cannot read are typos
            self.error(f"unrecognized arguments: {self._suggest(extras)}")
        return namespace, extras

    def _suggest(self, extras: list[str]) -> str:
        """The tokens, each mistyped option followed by the closest one it has."""
        known = [o for o in self._option_string_actions if o.startswith("--")]
        words, hinted = [], False
        for token in extras:
            flag = token.split("=", 1)[0]
            close = difflib.get_close_matches(flag, known, n=1, cutoff=0.6)
            if token.startswith("--") and close:
                words.append(f"{token} (did you mean {close[0]}?)")
                hinted = True
            else:
                words.append(token)
        return " ".join(words) + ("" if hinted else f"; `{self.prog} --help` lists the options")

    def error(self, message: str) -> Any:
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2))
            close = difflib.get_close_matches(m.group(1), choices, n=1, cutoff=0.5)
            if close:
                message += f"; did you mean {close[0]!r}?"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    import rlu.commands
    from rlu import __version__

    parser = Parser(
        prog="rlu",
        description="RL Unplugged: datasets, environments, baselines, evaluation.",
        epilog="exit codes: " + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items()),
    )
    parser.add_argument("--version", action="version", version=f"rlu {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(rlu.commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue  # a helper of other command modules (options they share), no command
        module = importlib.import_module(f"rlu.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    if sys.stdout is None:  # started with stdout closed (``rlu list >&-``): its output is dropped
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (lives as long as the process)
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # what was typed (rlu train --config)
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except BrokenPipeError:
        _drop_stdout()
        return 141
    except RluError as e:
        _say(f"rlu: error: {e}")
        return 2
    except OSError as e:  # the system refused a file: permissions, a full disk, a missing dir
        where = f"{e.filename}: " if e.filename else ""
        _say(f"rlu: error: {where}{e.strerror or e}; check the path and its permissions")
        return 2
    except KeyboardInterrupt:
        _say("rlu: interrupted")
        return 130
    except ModuleNotFoundError as e:  # an extra is missing: the one line that installs it
        extra = EXTRA_OF.get((e.name or "").partition(".")[0])
        if extra is None:
            raise
        from rlu.system import install_hint

        _say(f"rlu: error: rlu {args.command} needs {e.name} (the {extra} extra): "
             f"{install_hint(extra)}")  # fmt: skip
        return 2


EXTRA_OF = {
    "torch": "agents",
    "ray": "distributed",
    "google_crc32c": "release",
    "PIL": "release",
    "matplotlib": "report",
    "jinja2": "report",
    "jax": "jax",
    "imageio_ffmpeg": "video",
    "moviepy": "video",
}
for _domain in DOMAINS.values():  # each domain's env packages (rlu.domains), first one wins
    for _package in _domain.packages:
        EXTRA_OF.setdefault(_package, _domain.extra)
EXTRA_OF.update(extras_of_packages())  # the foreign formats' own (rlu.data.formats)
"""The extra that installs each optional module rlu imports (pyproject.toml's extras)."""


def _say(line: str) -> None:
    """One line on stderr, whatever the message holds (a library's multi-line text included)."""
    line = " ".join(part.strip() for part in line.splitlines() if part.strip())
    try:
        print(line, file=sys.stderr)
    except OSError:  # stderr closed too: nothing left to tell
        pass


def _drop_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush does not fail again."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a real file (captured in tests)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
