"""One set of flags across every ``sc3`` command (sc3_jax/commands/flags.py): a world model is ``--world-model``, a
store ``--data``, a batch ``--batch``, the sampler's steps ``--sample-steps`` (with one default), in every command and
subcommand of ``sc3_jax/cli.py``'s table, read off each one's ``--help``; an option a command does not take is refused
in one line that names the closest one it does."""
from __future__ import annotations

import dataclasses
import importlib
import re

import pytest
import tyro

from sc3_jax import cli
from sc3_jax.cli import main
from sc3_jax.commands import flags
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.world_model_defaults import SamplerSteps

# each shared idea: its one spelling, and what any option about it has in its name
IDEAS = {"world model": (flags.WORLD_MODEL, re.compile(r"world-model|checkpoint|^--models?$|^--wm$")),
         "store": (flags.DATA, re.compile(r"store|initial-conditions|dataset|^--data\.path$|^--root$")),
         "batch": (flags.BATCH, re.compile(r"batch")),
         "sampler steps": (flags.SAMPLE_STEPS, re.compile(r"sample.*steps"))}

# the commands that keep a positional argument, none of them a world model or a store to read: a results store of
# a sweep (report, rescore), a curve's spec, the weights convert reads in either format
POSITIONAL_KEPT = {"report", "rescore", "curve", "convert"}

# the commands that sample a world model to evaluate it: each has --sample-steps and --inverse-steps
SAMPLING = {"rollout", "diagnose", "plan", "sweep bench", "sweep bussing", "sweep episodes", "sweep so101"}


def _targets() -> dict[str, list[str]]:
    """Every command and subcommand of cli.MODULES: 'NAME' or 'NAME SUB' -> its argv head."""
    out = {}
    for name, module in cli.MODULES.items():
        subcommands = getattr(importlib.import_module(module), "SUBCOMMANDS", None)
        if subcommands is None:
            out[name] = [name]
        else:
            out.update({f"{name} {sub}": [name, sub] for sub in subcommands})
    return out


TARGETS = _targets()


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0, f"sc3 {' '.join(argv)} --help exited with {e.value.code}"
    return capsys.readouterr().out


def options(text: str) -> dict[str, str]:
    """Every option of a tyro ``--help`` (boxes one above another, drawn or not), with its help text up to the next
    option: an option's line starts in the box's first column, its help's continuation lines further in."""
    out, current, boxes = {}, None, False
    for line in re.sub(r"[│╭╮╰╯─]", " ", text).splitlines():
        row = line.strip()
        boxes = boxes or bool(re.fullmatch(r"([\w.-]+ )?options|positional arguments", row))
        if not boxes:  # the usage line and the description, which may name options too
            continue
        m = re.match(r"(?:-h, )?(--[a-z][\w.-]*)", row) if len(line) - len(line.lstrip()) <= 3 else None
        if m:
            current = m.group(1)
            out[current] = row
        elif current and row and len(line) - len(line.lstrip()) > 3:
            out[current] += " " + row
        else:
            current = None
    return out


def positionals(text: str) -> bool:
    return "positional arguments" in text


def problems(where: str, opts: dict[str, str], has_positionals: bool) -> list[str]:
    """What ``sc3 WHERE --help`` gets wrong: an option about a shared idea spelt otherwise than its one spelling, a
    positional argument where none is kept."""
    out = [f"sc3 {where}: {o} for the {idea}; the one spelling is {one}"
           for idea, (one, about) in IDEAS.items() for o in opts if about.search(o) and o != one]
    if has_positionals and where not in POSITIONAL_KEPT:
        out.append(f"sc3 {where}: takes a positional argument (world models and stores are options)")
    return out


@pytest.mark.parametrize("where", sorted(TARGETS))
def test_every_command_spells_each_shared_idea_one_way(where, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")  # one column of boxes: one option a line
    text = _help(TARGETS[where], capsys)
    opts = options(text)
    fields = flags.arity(_args(where))  # the help read whole: every field's option, and no other
    assert set(opts) - {"--help"} == {o for o in fields if not (o.startswith("--no-") and f"--{o[5:]}" in fields)}
    assert not problems(where, opts, positionals(text)), "\n".join(problems(where, opts, positionals(text)))


@pytest.mark.parametrize("where", sorted(TARGETS))
def test_an_option_misspelt_is_refused_in_one_line_naming_the_one_meant(where, capsys):
    """The command's first option (--help where it has none), its last letter dropped: exit status 2, one line, the
    option it meant."""
    meant = next(iter(flags.arity(_args(where))), "--help")
    for spelt in ([meant[:-1], "SOMEWHERE"], [f"{meant[:-1]}=SOMEWHERE"]):
        rc = main([*TARGETS[where], *spelt])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, (where, spelt, err)
        assert f"unknown option {meant[:-1]} (did you mean {meant}?" in err, (where, spelt, err)


@pytest.mark.parametrize("argv, option", [(["train", "--data.path", "d"], "--data"),
                                           (["train", "--data.batch-size=4"], "--batch")])
def test_a_config_field_set_by_an_option_of_the_command_is_refused_naming_the_option(argv, option, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"sc3 {argv[0]} sets it with {option}" in err, err


def test_a_config_field_misspelt_is_refused_in_one_line_where_a_command_takes_config_fields(capsys):
    assert main(["train", "--config", "tiny", "--train.stepz", "5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown option --train.stepz (did you mean --train.steps?" in err, err


def _args(where: str) -> type:
    """The options dataclass of ``sc3 WHERE``."""
    name, _, sub = where.partition(" ")
    module = importlib.import_module(cli.MODULES[name])
    return module.SUBCOMMANDS[sub] if sub else module.Args


def default(opts: dict[str, str], option: str) -> str:
    m = re.search(r"\(default: ([^)]*)\)", opts[option])
    assert m, f"{option}: no default shown in {opts[option]!r}"
    return m.group(1)


def test_the_sample_steps_default_is_the_same_everywhere(capsys, monkeypatch):
    """Every command that has --sample-steps (and --inverse-steps) shows the one default, SamplerSteps'; the ones
    that sample a world model all have them."""
    monkeypatch.setenv("COLUMNS", "120")
    shown = {}
    for where, argv in TARGETS.items():
        opts = options(_help(argv, capsys))
        for option in (flags.SAMPLE_STEPS, flags.INVERSE_STEPS):
            if option in opts:
                shown[where, option] = default(opts, option)
    assert {w for w, o in shown if o == flags.SAMPLE_STEPS} >= SAMPLING
    assert {w for w, o in shown if o == flags.INVERSE_STEPS} == {w for w, o in shown if o == flags.SAMPLE_STEPS}
    one = {flags.SAMPLE_STEPS: str(SamplerSteps.sample_steps), flags.INVERSE_STEPS: str(SamplerSteps.inverse_steps)}
    assert {k: v for k, v in shown.items() if v != one[k[1]]} == {}


def test_the_sampler_default_is_the_sweeps_and_none_reads_the_models_own():
    """2 forward steps and 1 inverse (the published sweeps', docs/sweep.md#sampler-steps); None: the model's own."""
    from sc3_jax.core.config import load_config, replace
    from sc3_jax.evaluation.world_model_defaults import Sampler, evaluation_config

    assert (SamplerSteps.sample_steps, SamplerSteps.inverse_steps) == (2, 1)
    own = replace(load_config("tiny"), sample=dict(steps=8, inverse_steps=None))
    assert evaluation_config(own, Sampler()).sample.steps == 2
    assert evaluation_config(own, Sampler(sample_steps=None, inverse_steps=None)).sample == own.sample


def test_train_demo_and_plan_set_the_configs_data_and_batch(tmp_path):
    """--data and --batch are data.path and data.batch_size for the commands that build a config, read as given on
    the command line where the data decide a field; the planner's hints spell them the same way."""
    from sc3_jax.train.config_flag import config_flag
    from sc3_jax.commands import demo, parse_with_config, train

    argv = ["--config", "tiny", "--data", str(tmp_path), "--batch", "4", "--data.image-size", "8", "8"]
    _, cfg = parse_with_config(train.Args, argv, "train", train.config_of)
    assert (cfg.data.path, cfg.data.batch_size, cfg.data.image_size) == (str(tmp_path), 4, (8, 8))
    assert flags.explicit_fields(argv) == {"data.path", "data.batch_size", "data.image_size"}
    _, cfg = parse_with_config(demo.Args, ["--out", str(tmp_path), "--batch", "3"], "demo", demo._config)
    assert cfg.data.batch_size == 3 and cfg.data.path == str(tmp_path / "episodes")
    assert {config_flag(field, 7) for field in flags.CONFIG_FIELDS.values()} == \
        {f"{option} 7" for option in flags.CONFIG_FIELDS}


def test_the_checks_catch_a_command_that_spells_a_shared_idea_another_way(capsys):
    """The walk above fails on a command whose options reintroduce --checkpoint, --batch-size or a positional
    store, and the refusal of unknown options stands aside for an option a command has."""
    @dataclasses.dataclass(frozen=True)
    class Back:
        checkpoint: str
        """a world model"""
        store: tyro.conf.Positional[str]
        """a store"""
        batch_size: int = 1
        """a batch"""

    with pytest.raises(SystemExit):
        tyro.cli(Back, args=["--help"], prog="sc3 back")
    text = capsys.readouterr().out
    found = problems("back", options(text), positionals(text))
    assert any("--checkpoint for the world model" in p for p in found)
    assert any("--batch-size for the batch" in p for p in found)
    assert any("positional argument" in p for p in found)
    flags.refuse_unknown("back", ["--checkpoint", "wm", "s"], Back)  # its own option: not refused
    @dataclasses.dataclass(frozen=True)
    class Now:
        out: str = "x"
        """where"""

    with pytest.raises(UserError, match="unknown option --checkpoint"):
        flags.refuse_unknown("back", ["--checkpoint", "wm"], Now)
