"""One module per ``sc3`` command: its options are a frozen dataclass ``Args`` parsed by tyro (each field's docstring
is its ``--help`` text), and ``main(argv) -> int`` calls the library functions. ``sc3_jax/cli.py`` dispatches here;
library modules keep functions, not ``main()``s."""
from __future__ import annotations

from typing import TypeVar

import tyro

T = TypeVar("T")


def parse(args: type[T], argv: list[str], command: str) -> T:
    """``argv`` as ``args``; positionals are named after their field (``RESULTS``, not ``STR``), as they were before
    the commands moved from argparse."""
    return tyro.cli(args, args=argv, prog=f"sc3 {command}", config=(tyro.conf.PositionalMetavarFromFieldName,))


def one_or_more(name: str):
    """For a positional ``tuple[str, ...]``: tyro parses it as zero or more values, shown optional; this shows it as
    argparse's ``nargs="+"`` did (the command itself refuses an empty one)."""
    return tyro.conf.arg(metavar=f"{name} [{name} ...]", help_behavior_hint="(required)")
