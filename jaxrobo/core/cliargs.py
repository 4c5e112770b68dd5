"""The argument parser of every ``jaxrobo`` command: a usage error is one line, as every other refusal is.

argparse's own ``error`` prints the whole usage block before the message, so ``jaxrobo train --n-envs abc`` read as
twenty lines of flags around the one that says what is wrong; every other bad input is refused in one line
(``jaxrobo train: ...``, exit 2). :class:`Parser` prints ``PROG: MESSAGE`` and exits 2 the same way; ``--help``
still prints the usage. Subcommands inherit it: ``add_subparsers`` makes its parsers of the parent's class.
"""
from __future__ import annotations

import argparse
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    """:class:`argparse.ArgumentParser` whose usage errors are one line: ``PROG: MESSAGE``, exit status 2."""

    def error(self, message: str) -> NoReturn:
        # One line even where argparse wraps a message (an invalid choice among many): the line is what is read.
        self.exit(2, f"{self.prog}: {' '.join(message.split())}\n")

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        parsed, extra = self.parse_known_args(args, namespace)
        if extra:  # named by the subcommand they were given to (`jaxrobo train: ...`), as its other errors are
            _chosen(self, parsed).error(f"unrecognized arguments: {' '.join(extra)}")
        return parsed


def _chosen(parser: argparse.ArgumentParser, parsed: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost subcommand parser ``parsed`` went through (``parser`` itself without subcommands)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            name = getattr(parsed, action.dest, None)
            if name in action.choices:
                return _chosen(action.choices[name], parsed)
    return parser
