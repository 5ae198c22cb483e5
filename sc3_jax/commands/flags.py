"""The one spelling of each idea the ``sc3`` commands share, and the one line that refuses the spellings before them.

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

The spellings before these (``OLD``, and the positional world models and stores of ``POSITIONAL``) are refused by
``refuse_old_spellings`` in one line that gives the command back respelt; ``commands.parse`` and
``commands.parse_with_config`` call it for every command, before tyro parses anything.
"""
from __future__ import annotations

import dataclasses
import shlex
import types
import typing

import tyro

from sc3_jax.core.errors import UserError

WORLD_MODEL, DATA, BATCH, SAMPLE_STEPS, INVERSE_STEPS = (
    "--world-model", "--data", "--batch", "--sample-steps", "--inverse-steps")

# spellings before the one set of flags -> the one spelling now
OLD = {"--checkpoint": WORLD_MODEL,
       "--initial-conditions": DATA, "--store": DATA, "--data.path": DATA,
       "--batch-size": BATCH, "--data.batch-size": BATCH,
       "--sample.steps": SAMPLE_STEPS, "--sample.inverse-steps": INVERSE_STEPS}

# commands whose world model or store was their positional argument -> the option it is now
POSITIONAL = {"diagnose": WORLD_MODEL, "train-state": WORLD_MODEL, "diagnose-table": WORLD_MODEL,
              "train-detector": DATA, "data import-lerobot": DATA, "data export-lerobot": DATA}

# commands whose store is their positional argument (sc3 report RESULTS): an old store flag is respelt as it
STORE_POSITIONAL = {"report": "RESULTS", "rescore": "RESULTS"}

# where a refused flag's new spelling lives when the command itself does not take it
ELSEWHERE = {SAMPLE_STEPS: "the sampler's steps are chosen where a world model is sampled: sc3 sweep, rollout, "
                           "diagnose, plan --sample-steps N (a config file's sample.steps is the model's own)",
             INVERSE_STEPS: "the sampler's steps are chosen where a world model is sampled: sc3 sweep, rollout, "
                            "diagnose, plan --inverse-steps N (a config file's sample.inverse_steps is the model's "
                            "own)"}

# the options of sc3 train / demo / plan that set a config field (every other field: --SECTION.FIELD VALUE)
CONFIG_FIELDS = {DATA: "data.path", BATCH: "data.batch_size"}

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


def _strays(argv: list[str], takes: dict[str, int]) -> list[int]:
    """Indices of the tokens of ``argv`` that no option takes as its value: positional arguments."""
    out, i = [], 0
    while i < len(argv):
        token = argv[i]
        i += 1
        if not _is_option(token):
            out.append(i - 1)
            continue
        n = 0 if "=" in token else takes.get(_name(token), GREEDY)
        while i < len(argv) and not _is_option(argv[i]) and (n == GREEDY or n > 0):
            i, n = i + 1, n if n == GREEDY else n - 1
    return out


def refuse_old_spellings(command: str, argv: list[str], args: type) -> None:
    """A one-line UserError when ``argv`` (of ``sc3 COMMAND``, whose options are the dataclass ``args``) spells a
    world model, store, batch or sampler steps as before (``OLD``, or a positional where ``POSITIONAL`` names the
    option it became): it names the new option and gives the command back respelt, or, where the command does not
    take the new option, says where it lives."""
    takes = arity(args)
    said, fixed = [], list(argv)
    for i, token in enumerate(argv):
        new = OLD.get(_name(token))
        if new is not None and _name(token) not in takes:
            said.append((_name(token), new))
            fixed[i] = new + token[len(token.split("=", 1)[0]):]
    strays = _strays(argv, takes) if command in POSITIONAL else []
    if strays:
        new = POSITIONAL[command]
        said.append(("the positional " + " ".join(argv[i] for i in strays), new))
        fixed = [t for i, t in enumerate(fixed) if i not in strays]
        fixed[strays[0]:strays[0]] = [new] + [argv[i] for i in strays]
    if not said:
        return
    missing = sorted({new for _, new in said if new not in takes})
    what = ", ".join(f"{old} is now {new}" for old, new in said)
    if missing == [DATA] and command in STORE_POSITIONAL:
        # the store is this command's positional argument: the value moves there, not to an option it does not take
        values, rest, i = [], [], 0
        while i < len(argv):
            t, i = argv[i], i + 1
            if OLD.get(_name(t)) not in missing:
                rest.append(t)
            elif "=" in t:
                values.append(t.split("=", 1)[1])
            elif i < len(argv):
                values, i = values + [argv[i]], i + 1
        raise UserError(f"{what}, which sc3 {command} does not take: its store is the positional "
                        f"{STORE_POSITIONAL[command]}: sc3 {command} {shlex.join(values + rest)}")
    if missing:
        where = "; ".join(ELSEWHERE.get(m, f"`sc3 {command} --help` lists its options") for m in missing)
        raise UserError(f"{what}, which sc3 {command} does not take: {where}")
    raise UserError(f"{what}: sc3 {command} {shlex.join(fixed)}")


def respell(argv: list[str]) -> list[str]:
    """``argv`` with every ``OLD`` option in its new spelling (values kept)."""
    return [OLD[_name(t)] + t[len(t.split("=", 1)[0]):] if _name(t) in OLD else t for t in argv]


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
