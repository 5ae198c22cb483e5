"""``sc3 train --config NAME [--data STORE] [--batch N] [--SECTION.FIELD VALUE ...]``: train (or resume) a world
model."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from sc3_jax.commands import parse_with_config
from sc3_jax.commands.flags import explicit_fields, onto_config

PREEMPTED = 143  # 128 + SIGTERM, as a shell reports a process the signal ended

SUMMARY = "train (or resume) a world model from a named config or a config file"  # the line `sc3 --help` shows
# the line Ctrl-C ends with (cli.py; every writer is atomic)
RESUME = "the same command resumes from its last checkpoint"


@dataclasses.dataclass(frozen=True)
class Args:
    """Train a world model, or resume it exactly (rerun the same command). The model's views, image size and action
    dimension are read from the dataset (--data: its dataset.json) unless given. Every other field of the config is
    an option: --SECTION.FIELD VALUE, e.g. --train.steps 100 --train.workdir runs/mine (the list: `sc3 train --config
    NAME --help-config`)."""

    config: str = "tiny"
    """a named config (`sc3 configs`) or a config file, optionally NAME:ARG (passed to its get_config)"""
    data: str | None = None
    """the episode store to train on (the config's data.path; None: the config's)"""
    batch: int | None = None
    """global batch, summed over processes and devices (the config's data.batch_size; None: the config's, sized
    from the data)"""
    help_config: bool = False
    """list every --SECTION.FIELD option of the config, with its value in NAME, and exit"""


def main(argv: list[str]) -> int:
    import tyro

    from sc3_jax.core.config import Config

    a, cfg = parse_with_config(Args, argv, "train", config_of)
    if a.help_config:
        tyro.cli(Config, default=cfg, args=["--help"], prog=f"sc3 train --config {a.config}")
    from sc3_jax.core import validate

    validate.train_config(cfg)  # every numeric field in bounds, the workdir a directory: before anything is read
    from sc3_jax.model import saved_model

    saved_model.check_options(cfg)  # and the model's sizes (--model.dim -192 was a JAX TypeError)
    import jax

    from sc3_jax.train import sizing, train
    from sc3_jax.data.shape import shape_from_dataset

    # views, image size and action dimension come from the dataset unless given here (then they are checked)
    # (no dataset there: train() says so, after refusing a changed config, which it checks first)
    declared = cfg
    if (Path(cfg.data.path) / "dataset.json").is_file():
        cfg = shape_from_dataset(cfg, cfg.data.path, explicit_fields(argv))
        old = _saved_config(cfg)
        if old is not None:  # a run started before its config recorded the data's fps / state: resumed as saved
            cfg = _keep(cfg, old, ROBOT_FIELDS, explicit_fields(argv))
    _check_tokenizer(cfg)
    cfg = _sized(cfg, declared, explicit_fields(argv))
    cfg = _memory_plan(cfg, explicit_fields(argv))
    print(sizing.describe(sizing.cost(cfg, jax.device_count())), flush=True)
    last = train.train(cfg)
    if last.get("step") is not None and last["step"] < cfg.train.steps:  # SIGTERM (a scheduler's preemption)
        print(f"stopped at step {last['step']} of {cfg.train.steps} (SIGTERM): its checkpoint is saved; rerun the "
              f"same command to resume -> {cfg.train.workdir}", flush=True)
        return PREEMPTED  # not "done", and the learned state is not trained on a half-trained model
    if last.get("step") is None:  # resumed at or past --train.steps: the loop ran no step
        print(f"done: {cfg.train.workdir} already holds --train.steps {cfg.train.steps}; nothing to train")
    else:
        print(f"done: step {last['step']} loss {last.get('loss', float('nan')):.4f} -> {cfg.train.workdir}")
    from sc3_jax.data.episodes import EpisodeStore

    has_state = (Path(cfg.data.path) / "dataset.json").is_file() and EpisodeStore(cfg.data.path).state_dim
    if has_state:  # the robot records its state: the policies acting inside the world model will read it
        from sc3_jax.commands import train_state
        from sc3_jax.rollout.state_head import FitConfig

        print(train_state.describe(*train_state.train(cfg.train.workdir, None, FitConfig(), cfg.train.progress)))
    return 0


def config_of(a: Args):
    """The named config with --data and --batch set (before the --SECTION.FIELD overrides)."""
    from sc3_jax.core.config import load_config

    return onto_config(load_config(a.config), a.data, a.batch)


def _check_tokenizer(cfg) -> None:
    """A learned-tokenizer config without its tokenizer: the one command that makes it, not a traceback."""
    m = cfg.model
    if m.tokenizer == "conv_ae" and not (m.tokenizer_path and (Path(m.tokenizer_path) / "ae.json").is_file()):
        from sc3_jax.core.errors import UserError
        raise UserError(
            f"--config {cfg.name} reads frames through a trained tokenizer, and model.tokenizer_path={m.tokenizer_path}"
            f" holds none: train it first (sc3 train-tokenizer --data {cfg.data.path} --workdir TOK), then add "
            "--model.tokenizer-path TOK/tokenizer; or train on pixel patches with no tokenizer: --config tiny")


ROBOT_FIELDS = (("data", "fps"), ("data", "state_dim"))  # facts a saved model reads back (checkpoint.read_robot)
SIZED_FIELDS = (("model", "frame_tokens"), ("model", "patch_size"), ("data", "batch_size"))


def _sized(cfg, declared, explicit):
    """The config sized from its data (``sizing.size_from_data``), printing what changed; a resumed run keeps the
    size its workdir was started with (the sizing reads a lowered step's FLOPs, which need not land on the same side
    of its threshold on another machine; a run must resume with the config it started with)."""
    from sc3_jax.train import sizing

    old = _saved_config(cfg)
    if old is not None:
        return _keep(cfg, old, SIZED_FIELDS, explicit)
    cfg, note = sizing.size_from_data(cfg, declared, explicit)
    if note:
        print(note)
    return cfg


def _saved_config(cfg) -> dict | None:
    """The workdir's config.json (a run to resume) as a dict, or None for a fresh run."""
    from sc3_jax.core import atomic
    from sc3_jax.core.validate import json_object

    saved = Path(cfg.train.workdir) / "config.json"
    if not saved.is_file():
        return None
    return json_object(atomic.read_json(saved), str(saved), "restore it, or train into a new --train.workdir")


def _keep(cfg, old: dict, fields, explicit):
    """``cfg`` with ``fields`` ((section, field) pairs) as the saved run has them, unless the command line names them
    (a field the saved run predates keeps its default)."""
    from sc3_jax.core.config import replace

    for sec, f in fields:
        if f"{sec}.{f}" not in explicit:
            section = old.get(sec) if isinstance(old.get(sec), dict) else {}
            cfg = replace(cfg, **{sec: {f: section.get(f, getattr(type(getattr(cfg, sec))(), f))}})
    return cfg


MEMORY_FIELDS = (("model", "attention_impl"), ("model", "remat"), ("train", "grad_accum"))


def _memory_plan(cfg, explicit):
    """A step that cannot fit this machine: the memory plan that does (``memory.fit_to_memory``: the same model and
    math), or one line saying why not, before anything compiles -- never an allocator failure. A resumed run keeps
    the plan its workdir was started with (free memory changes between runs; its config must not)."""
    import jax

    from sc3_jax.train import memory

    old = _saved_config(cfg)
    if old is not None:
        return _keep(cfg, old, MEMORY_FIELDS, explicit)
    cfg, note = memory.fit_to_memory(cfg, jax.device_count(), explicit)
    if note:
        print(note)
    return cfg
