"""The one spelling of each idea the ``sc3`` commands share, and the one line that refuses an option a
command does not take.

    --world-model DIR   a saved world model (a `sc3 train` workdir or an exported one): sc3 rollout, diagnose,
                        train-state, diagnose-table (one or more), sweep bench|episodes|so101
    --data DIR          a store: an episode store, initial conditions, a dataset to import, train or measure on
                        (sc3 train / plan: the config's data.path)
    --batch N           a batch size: episodes, conditions, frames or images per step or per call (sc3 train / demo /
                        plan: the config's data.batch_size)
    --sample-steps N    the sampler's forward Euler steps wherever a world model is sampled to be evaluated: sc3 sweep
                        bench|episodes|so101, rollout, diagnose, plan (its rollout chunk); --inverse-steps N the
                        steps of the inverse-dynamics re-read that yields U_chunk

The sampler's default is defined once, ``world_model_defaults.SamplerSteps`` (2 forward steps, 1 inverse), and
every command that has the options inherits it. It is the evaluation protocol's, not a saved model's own
``sample.steps`` (the shipped models record 8, their training configs' value): every published sweep of the shipped
models ran at 2 (docs/sweep.md#sampler-steps, where 2 are within the paired interval of 8), and a tau or a U read in
one command must be read alike in the others. ``--sample-steps None`` samples in the world model's own steps (its
``config.json`` ``sample.steps``), ``--inverse-steps None`` likewise. ``sc3 train`` and ``sc3 demo`` sample nothing
that is evaluated: the model's own steps are its config file's ``sample.steps``.

An option the command does not take is refused in one line that names the closest one it does take (``refuse_unknown``;
``commands.parse`` and ``commands.parse_with_config`` call it for every command, before tyro parses anything).
"""
from __future__ import annotations

import dataclasses
import difflib
import types
import typing

import tyro

from sc3_jax.core.errors import UserError

WORLD_MODEL, DATA, BATCH, SAMPLE_STEPS, INVERSE_STEPS = (
    "--world-model", "--data", "--batch", "--sample-steps", "--inverse-steps")

# the options of sc3 train / demo / plan that set a config field (every other field: --SECTION.FIELD VALUE)
CONFIG_FIELDS = {DATA: "data.path", BATCH: "data.batch_size"}

# config fields that a command's own option sets where it has that option: given as --SECTION.FIELD too, one would
# silently override the other, so the field is refused there, naming the option
SET_BY_OPTION = {"--data.path": DATA, "--data.batch-size": BATCH, "--sample.steps": SAMPLE_STEPS,
                 "--sample.inverse-steps": INVERSE_STEPS}

GREEDY = -1  # an option taking any number of values (a tuple), or a config override whose arity is not known here


def _name(token: str) -> str:
    """``--data.batch_size=8`` -> ``--data.batch-size``: the option a token names, as tyro reads either case."""
    return token.split("=", 1)[0].replace("_", "-")


def _is_option(token: str) -> bool:
    return token.startswith("--") or token == "-h"


def _unwrap(hint):
    """(the type under Annotated and Optional, the Annotated metadata)."""
    meta = []
    while True:
        if typing.get_origin(hint) is typing.Annotated:
            meta += list(hint.__metadata__)
            hint = hint.__origin__
        elif typing.get_origin(hint) in (typing.Union, types.UnionType):
            rest = [h for h in typing.get_args(hint) if h is not type(None)]
            if len(rest) != 1:
                return hint, meta
            hint = rest[0]
        else:
            return hint, meta


def arity(args: type, prefix: str = "") -> dict[str, int]:
    """Option -> how many values it takes, for every field of the dataclass ``args`` as tyro spells it (booleans
    take none, variable tuples any number: ``GREEDY``); nested dataclasses as --SECTION.FIELD. A positional field has
    no option."""
    try:
        hints = typing.get_type_hints(args, include_extras=True)
    except (NameError, TypeError):  # an annotation that does not resolve here: nothing known, every value greedy
        return {}
    out = {}
    for f in dataclasses.fields(args):
        hint, meta = _unwrap(hints[f.name])
        if any(m is tyro.conf.Positional for m in meta):
            continue
        names = [m.name for m in meta if isinstance(getattr(m, "name", None), str)]
        flag = "--" + prefix + (names[0] if names else f.name).replace("_", "-")
        if dataclasses.is_dataclass(hint):
            out.update(arity(hint, prefix + f.name + "."))
        elif hint is bool:
            out[flag] = 0
            out["--" + prefix + "no-" + flag[2 + len(prefix):]] = 0
        elif typing.get_origin(hint) is tuple:
            inner = typing.get_args(hint)
            out[flag] = GREEDY if (not inner or inner[-1] is Ellipsis) else len(inner)
        else:
            out[flag] = 1
    return out


def refuse_unknown(command: str, argv: list[str], *args: type) -> None:
    """A one-line UserError naming the first option of ``argv`` that none of the dataclasses ``args`` (a command's
    options, and the config whose ``--SECTION.FIELD`` it takes) spells, with the closest one that is (tyro's own
    refusal is a box of many lines), or a config field the command sets with an option of its own
    (``SET_BY_OPTION``). Nothing unknown is refused where an annotation does not resolve here (nothing known)."""
    own = {_name(o) for o in arity(args[0])}
    for token in argv:
        if SET_BY_OPTION.get(_name(token)) in own:
            raise UserError(f"{_name(token)}: sc3 {command} sets it with {SET_BY_OPTION[_name(token)]}")
    known = {"--help", "-h"}
    for a in args:
        try:
            typing.get_type_hints(a, include_extras=True)
        except (NameError, TypeError):  # arity() knows nothing of it: tyro refuses what it does not take
            return
        known |= {_name(o) for o in arity(a)}
    for token in argv:
        if token.startswith("--") and _name(token) not in known:
            close = difflib.get_close_matches(_name(token), sorted(known), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]}? " if close else ""
            raise UserError(f"unknown option {_name(token)} ({hint}sc3 {command} --help lists them)")


def onto_config(cfg, data: str | None, batch: int | None):
    """``cfg`` with ``--data`` / ``--batch`` of sc3 train, demo or plan set (``CONFIG_FIELDS``); None: the config's."""
    from sc3_jax.core.config import replace

    given = {field.split(".")[1]: v for field, v in ((CONFIG_FIELDS[DATA], data), (CONFIG_FIELDS[BATCH], batch))
             if v is not None}
    return replace(cfg, data=given) if given else cfg


def explicit_fields(argv: list[str]) -> frozenset[str]:
    """The ``section.field`` names a command line of sc3 train / plan sets (``data.shape.explicit_fields``), its
    ``--data`` and ``--batch`` read as the config fields they set."""
    from sc3_jax.data.shape import explicit_fields as dotted

    return dotted(["--" + CONFIG_FIELDS[_name(t)] if _name(t) in CONFIG_FIELDS else t for t in argv])
