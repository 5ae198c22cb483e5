"""One module per ``sc3`` command: its options are a frozen dataclass ``Args`` parsed by tyro (each field's docstring
is its ``--help`` text), and ``main(argv) -> int`` calls the library functions. A command with subcommands (``sc3
sim``, ``sc3 data``) has ``SUBCOMMANDS = {name: Args}`` instead. ``sc3_jax/cli.py`` dispatches here, and to a
benchmark's own commands, which keep the same contract in ``sc3_jax/benchmarks/NAME/commands/CMD.py`` (``sc3 CMD``);
``RESUME``, where a command has one, is what the line Ctrl-C leaves says a rerun keeps. Library modules keep
functions, not ``main()``s.

Every command that builds or loads a world model takes its config's fields the same way: ``--SECTION.FIELD VALUE``
(``sc3 train --help`` lists them all), applied over the named config or the loaded world model's config
(``parse_with_config``). The options every command shares have one spelling each (``--world-model``, ``--data``,
``--batch``, ``--sample-steps``: ``flags.py``); ``parse`` and ``parse_with_config`` refuse an option the command
does not take in one line, naming the closest one it does."""
from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TypeVar

import tyro

from sc3_jax.commands.flags import refuse_unknown

T = TypeVar("T")

CONFIG_OVERRIDES = ("World-model config: any --SECTION.FIELD VALUE of `sc3 train --help` overrides the model's own "
                    "config, e.g. --rollout.tau 0.05 --rollout.episode-seconds 6.")


def parse(args: type[T], argv: list[str], command: str) -> T:
    """``argv`` as ``args``; positionals are named after their field (``RESULTS``, not ``STR``), as they were before
    the commands moved from argparse. An option ``args`` does not have is refused first, in one line."""
    refuse_unknown(command, argv, args)
    return tyro.cli(args, args=argv, prog=f"sc3 {command}", config=(tyro.conf.PositionalMetavarFromFieldName,))


def parse_with_config(args: type[T], argv: list[str], command: str, base: Callable[[T], object]):
    """(``args``, Config): the command's own options, then every ``--SECTION.FIELD VALUE`` left over applied to
    ``base(parsed args)`` (the named config, or the config of the world model the command loads). One spelling of
    config overrides for every command; an option neither ``args`` nor the config has is refused first, in one line."""
    from sc3_jax.core.config import Config

    refuse_unknown(command, argv, args, Config)
    a, rest = tyro.cli(args, args=argv, prog=f"sc3 {command}", return_unknown_args=True,
                       config=(tyro.conf.PositionalMetavarFromFieldName,))
    cfg = base(a)
    if rest:
        cfg = tyro.cli(Config, default=cfg, args=rest, prog=f"sc3 {command}")
    return a, cfg


def parse_evaluated(args: type[T], argv: list[str], command: str):
    """``parse_with_config`` for a command that samples a saved world model (``--world-model``; ``args`` inherits
    ``world_model_defaults.SamplerSteps``): its config under the evaluation sampler (``--sample-steps`` and
    ``--inverse-steps``, whose defaults are the sweeps'), then the ``--SECTION.FIELD`` overrides; a distilled student
    sampled off its one step is warned about."""
    from sc3_jax.model import checkpoint
    from sc3_jax.evaluation.world_model_defaults import Sampler, evaluation_config, warn_if_student_off_its_step

    a, cfg = parse_with_config(args, argv, command, lambda a: evaluation_config(
        checkpoint.read_config(a.world_model), Sampler(sample_steps=a.sample_steps, inverse_steps=a.inverse_steps)))
    warn_if_student_off_its_step(cfg)
    return a, cfg


def one_or_more(name: str):
    """For a ``tuple[str, ...]`` that needs a value at least (a positional, or an option without a default): shows it
    as argparse's ``nargs="+"`` did (the command itself refuses an empty one)."""
    return tyro.conf.arg(metavar=f"{name} [{name} ...]", help_behavior_hint="(required)")


def run_group(group: str, about: str, subcommands: dict[str, type], run: dict[str, Callable], argv: list[str]) -> int:
    """``sc3 GROUP SUB [OPTIONS]``: ``--help`` lists the subcommands (each Args docstring's first line); a missing or
    unknown one is a usage error (status 2) with the list; else ``run[SUB](parse(subcommands[SUB], ...))``."""
    width = max(map(len, subcommands))
    listing = "subcommands:\n" + "\n".join(f"  {n:<{width}}  {a.__doc__.strip().splitlines()[0]}"
                                           for n, a in subcommands.items())
    usage = f"usage: sc3 {group} SUBCOMMAND [OPTIONS]   (sc3 {group} SUBCOMMAND --help for its options)"
    if argv and argv[0] in ("-h", "--help"):
        print(f"{usage}\n\n{about}\n\n{listing}")
        return 0
    if not argv or argv[0] not in subcommands:
        what = f"unknown subcommand {argv[0]!r}" if argv else "missing subcommand"
        print(f"{usage}\nsc3 {group}: error: {what}\n\n{listing}", file=sys.stderr)
        return 2
    return run[argv[0]](parse(subcommands[argv[0]], argv[1:], f"{group} {argv[0]}"))
