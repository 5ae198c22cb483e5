"""``sc3 plan --config NAME --mesh data=..,fsdp=.. --device DEVICE [--data STORE] [--batch N] [--sample-steps N]
[--SECTION.FIELD VALUE ...]``: what a config costs on a mesh of accelerators, without allocating the model."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

from sc3_jax.commands import parse_with_config
from sc3_jax.commands.flags import onto_config
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.world_model_defaults import Sampler, SamplerSteps, evaluation_config
from sc3_jax.train.plan import DEVICES  # plan.py imports jax only inside its functions

SUMMARY = "what a config costs on a mesh of accelerators (memory, FLOPs, step time)"  # the line `sc3 --help` shows

Device = Literal[tuple(DEVICES)]


@dataclasses.dataclass(frozen=True)
class Args(SamplerSteps):
    """What a config costs on a mesh of accelerators: parameters, per-device memory of the train step, FLOPs per
    step and per rollout chunk (sampled as the sweeps sample: --sample-steps, --inverse-steps; None: the config's
    own), and the times they imply; whether it fits, and if not, the options that make it fit. Nothing is allocated
    (abstract shapes, lowered programs). Every other field of the config is an option too: --SECTION.FIELD VALUE,
    e.g. --model.attention-impl ring (the list: --help-config). Views, image size and action dimension are the
    config's, or with --data STORE its dataset.json's (as `sc3 train` reads them; fields given on the command line
    are checked against it instead)."""

    config: str = "tiny"
    """a named config (`sc3 configs`) or a config file, optionally NAME:ARG (passed to its get_config)"""
    data: str | None = None
    """an episode store whose dataset.json gives the views, image size and action dimension (the config's
    data.path; None: the config's own shape, its data.path not read)"""
    batch: int | None = None
    """global batch (the config's data.batch_size; None: the config's)"""
    mesh: str = "data=1"
    """the planned mesh, AXIS=SIZE,... over data, fsdp, tensor, context (missing axes = 1); it replaces the config's
    mesh section"""
    device: Device = "h100"
    """the accelerator: its approximate vendor dense-BF16 peak and memory per chip (plan.DEVICES)"""
    mfu: float = 0.4
    """assumed fraction of the device's peak FLOP/s that the times are computed at"""
    compile: bool = False
    """compile (CPU-cheap configs only): exact bench/train_step.py FLOPs and, if the mesh fits on this machine's
    devices, measured per-device activation memory"""
    chunk: bool = True
    """estimate one rollout chunk's FLOPs and time (--no-chunk skips it)"""
    help_config: bool = False
    """list every --SECTION.FIELD option of the config, with its value in NAME, and exit"""


def _refuse_mesh_fields(argv: list[str]) -> None:
    """`--mesh.AXIS N` sets the training config's mesh, which the plan would ignore (--mesh names the planned mesh):
    refused with the spelling to use."""
    for token in argv:
        if token.startswith("--mesh."):
            raise UserError(f"{token}: the planned mesh is --mesh AXIS=SIZE,... (e.g. --mesh data=4,fsdp=8,context=2)")


def main(argv: list[str]) -> int:
    import tyro

    from sc3_jax.core.config import Config

    _refuse_mesh_fields(argv)
    a, cfg = parse_with_config(Args, argv, "plan", config_of)
    if a.help_config:
        tyro.cli(Config, default=cfg, args=["--help"], prog=f"sc3 plan --config {a.config}")
    from sc3_jax.train import plan

    # the rollout chunk as the sweeps sample it (the config's own sample.steps where --sample-steps None)
    cfg = evaluation_config(cfg, Sampler(sample_steps=a.sample_steps, inverse_steps=a.inverse_steps,
                                         tau_units=cfg.rollout.tau_units))
    cfg, store = _shape_from_store(cfg, argv, a.data)
    # a store's action space is the rollout's, its frame rate the rollout's frame stride; without one the config's
    # data.fps where it records it, and no action kind (shape_check.cost_robot: a chunk's cost depends on neither)
    space, fps = (None, cfg.data.fps) if store is None else (store.action_space, float(store.fps))
    p = plan.plan(cfg, plan.parse_mesh(a.mesh), a.device, a.mfu, a.compile, a.chunk, action_space=space,
                  data_fps=fps)
    print(plan.format_plan(p))  # ends with the verdict: fits or not, why, and the options that make it fit
    return 0


def config_of(a: Args):
    """The named config with --data and --batch set (before the --SECTION.FIELD overrides)."""
    from sc3_jax.core.config import load_config

    return onto_config(load_config(a.config), a.data, a.batch)


def _shape_from_store(cfg, argv: list[str], data: str | None):
    """(config, store or None): with --data STORE given, views, image size and action dimension from
    its dataset.json the way `sc3 train` takes them (data.shape.shape_from_dataset); else the config's own shape
    (a config's default data.path is not read: a plan is for the config as written)."""
    from sc3_jax.commands.flags import explicit_fields
    from sc3_jax.data.shape import shape_from_dataset

    if data is None:
        return cfg, None
    if not (Path(cfg.data.path) / "dataset.json").is_file():
        raise UserError(f"--data {cfg.data.path}: no dataset.json there (not an sc3 episode store: `sc3 data "
                        "import-lerobot` writes one); leave --data out to plan the config's own shape")
    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(cfg.data.path)
    return shape_from_dataset(cfg, store, explicit_fields(argv)), store
