"""What every command shares: the parser class (usage errors: exit 2, one line), help that shows
each option's default and an example, and the value checks of numeric options."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # usage errors are input errors: exit 2, one line
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and examples as written; every option says its default, or that it is
    required."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is argparse.SUPPRESS or "default:" in text or "%(default)" in text:
            return text
        if action.option_strings == [] or isinstance(
            action, (argparse._HelpAction, argparse._VersionAction)
        ):
            return text
        if action.required:
            return f"{text} (required)"
        if isinstance(action, argparse._StoreTrueAction):
            return f"{text} (default: off)"
        if action.default is None:
            return f"{text} (default: none)"
        return f"{text} (default: %(default)s)"


def add_command(
    sub: argparse._SubParsersAction[argparse.ArgumentParser],
    name: str,
    summary: str,
    *,
    examples: Sequence[str],
    description: str | None = None,
) -> argparse.ArgumentParser:
    """A sub-command whose help has a description and at least one example."""
    lines = "\n".join(f"  {example}" for example in examples)
    return sub.add_parser(
        name,
        help=summary,
        description=description or summary[:1].upper() + summary[1:] + ".",
        epilog=f"example{'s' if len(examples) > 1 else ''}:\n{lines}",
        formatter_class=HelpFormatter,
    )


def add_subcommands(
    parser: argparse.ArgumentParser, dest: str
) -> argparse._SubParsersAction[argparse.ArgumentParser]:
    return parser.add_subparsers(dest=dest, required=True, parser_class=Parser, metavar="COMMAND")


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number ({what})") from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError(f"{text!r}: not a number (NaN); give {what}")
    if math.isinf(value):
        raise argparse.ArgumentTypeError(f"{text!r}: infinite; give {what}")
    return value


def finite(what: str) -> Callable[[str], float]:
    """A type for options that take any finite number."""

    def parse(text: str) -> float:
        return _number(text, what)

    parse.__name__ = what
    return parse


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a seed is a whole number >= 0")
    return value


def row_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give a number of rows >= 1")
    return value


def port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a TCP port (1 to 65535)")
    return value


def seconds(text: str) -> float:
    value = _number(text, "a number of seconds >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give a number of seconds >= 0")
    return value


def speed(text: str) -> float:
    value = _number(text, "a speed factor above 0 and at most 10000")
    if not 0 < value <= 10_000:
        raise argparse.ArgumentTypeError(f"{text!r}: a speed factor is above 0 and at most 10000")
    return value
