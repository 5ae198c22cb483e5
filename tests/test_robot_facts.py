"""Robot facts live with the model, never as a function default (docs/architecture.md).

Nothing robot-specific lives outside a benchmark (``sc3_jax/benchmarks/``): the action space, the cameras (views),
the data's frame rate and the termination threshold tau (set in an action space's raw units) come from the data or
the saved model (``checkpoint.read_robot``), never from a parameter's default.

(a) every function, method and dataclass field of every module of ``sc3_jax`` outside ``sc3_jax/benchmarks/``: a
    parameter named like one of those facts has no default, or None / () ("from the data / the model"), or an
    entry in ``ALLOWED`` with its reason;
(b) a saved tiny model records its robot facts (fps, action space, views, state size) and a rollout reads them
    back: they are the store's dataset.json's.
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import pkgutil
import re

import pytest

import sc3_jax

FACT = re.compile(r"(.*fps.*|.*_hz|action_space|space|views|view_names|cameras|tau|taus)$")
EXCLUDED = ("sc3_jax.benchmarks",)  # a benchmark's own facts are its to state

# (qualified name, parameter) -> why its default is not a robot fact. Keep short: each entry is a debt or a reason.
ALLOWED = {
    ("sc3_jax.core.config.DataConfig", "views"):
        "debt: the synthetic demo data's views, which data-less configs (tiny, paper, bussing_sim, bussing_latent, "
        "cpu_medium) size from; `sc3 train` replaces it from dataset.json (data/shape.py). () breaks those configs, "
        "convert_cli's Config(model=...), and tests building DataConfig without views (data_pipeline, init_from, "
        "sharding, autoencoder, self_forcing, flow_levers, pose_and_context_noise, ...)",
    ("sc3_jax.core.config.ModelConfig", "fps"):
        "cosmos3 layout's time-position scale (a model hyperparameter fixed at training; read back from config.json)",
    ("sc3_jax.core.config.ModelConfig", "base_fps"):
        "cosmos3 layout's time-position scale (a model hyperparameter fixed at training; read back from config.json)",
    ("sc3_jax.core.config.RolloutConfig", "control_hz"):
        "the rollout's model frame rate, an evaluation setting (the paper's 10 Hz protocol: stride = data fps / "
        "control_hz, checked against the model's data fps in rollout.make_spec; saved in config.json), not a fact of "
        "the robot. None as 'the data's fps' would change what it means (stride 1, not 2, on 20 Hz data) and need "
        "resolving in its ~15 readers (rollout, diagnose, policy_hz, the sweeps)",
}


def neutral(name: str, default) -> bool:
    """A default that states no robot fact: None or () ("from the data / the saved model"), a switch (a bool, e.g.
    model.fps_modulation), and for tau inf / (inf,) (no early termination: assumes no action space's units)."""
    if default is None or isinstance(default, bool) or (isinstance(default, tuple) and not default):
        return True
    if name in ("tau", "taus"):
        vals = default if isinstance(default, tuple) else (default,)
        return all(isinstance(v, float) and v == math.inf for v in vals)
    return False


def _modules():
    """Every module of the package outside the benchmarks, imported (an optional extra not installed: skipped)."""
    out = []
    for info in pkgutil.walk_packages(sc3_jax.__path__, "sc3_jax."):
        if info.name.startswith(EXCLUDED):
            continue
        try:
            out.append(importlib.import_module(info.name))
        except ModuleNotFoundError as e:  # an optional dependency (mujoco, torch, lerobot, ...) absent here
            if (e.name or "").startswith("sc3_jax"):
                raise
    return out


def _callables(mod):
    """(qualified name, callable) of every function and class defined in ``mod``, and of every method its classes
    define."""
    for name, obj in vars(mod).items():
        if getattr(obj, "__module__", None) != mod.__name__:
            continue
        if inspect.isfunction(obj):
            yield f"{mod.__name__}.{name}", obj
        elif inspect.isclass(obj):
            yield f"{mod.__name__}.{name}", obj  # its constructor: dataclass fields, __init__ parameters
            for attr, member in vars(obj).items():
                fn = member.__func__ if isinstance(member, (staticmethod, classmethod)) else member
                if inspect.isfunction(fn) and attr != "__init__":
                    yield f"{mod.__name__}.{name}.{attr}", fn


def _defaults(obj):
    """{parameter: default} of ``obj``'s signature (a dataclass's fields with their default factories' values)."""
    out = {}
    if dataclasses.is_dataclass(obj) and inspect.isclass(obj):
        for f in dataclasses.fields(obj):
            if f.default is not dataclasses.MISSING:
                out[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                out[f.name] = f.default_factory()
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):  # builtins, some C-backed classes
        return out
    for p in sig.parameters.values():
        if p.default is not inspect.Parameter.empty:
            out.setdefault(p.name, p.default)
    return out


def violations(modules) -> list[str]:
    bad = []
    for mod in modules:
        for qual, obj in _callables(mod):
            for name, default in _defaults(obj).items():
                if not FACT.match(name) or neutral(name, default):
                    continue
                if (qual, name) in ALLOWED:
                    continue
                bad.append(f"{qual}({name}={default!r})")
    return sorted(set(bad))


def test_no_robot_fact_is_a_default():
    bad = violations(_modules())
    assert not bad, ("robot facts given as defaults outside sc3_jax/benchmarks/ (take them from the data or the "
                     "saved model, checkpoint.read_robot; or justify in ALLOWED):\n  " + "\n  ".join(bad))


def test_every_allowed_entry_is_still_there():
    """An allowlist entry whose default went away is removed with it (the list stays short)."""
    mods = {m.__name__: m for m in _modules()}
    found = {(q, n) for m in mods.values() for q, obj in _callables(m) for n in _defaults(obj)}
    assert not set(ALLOWED) - found, sorted(set(ALLOWED) - found)


def test_the_check_catches_a_default():
    """The scan sees a robot fact given as a default (today's code had dozens: data_fps=20.0, DELTA_EE, ...)."""
    import types

    from sc3_jax.data.action_space import DELTA_EE

    mod = types.ModuleType("sc3_jax.fake")
    mod.DELTA_EE = DELTA_EE
    exec("def f(x, data_fps=20.0, space=None, views=()):\n    pass\n"  # noqa: S102
         "class C:\n    def m(self, action_space=DELTA_EE, tau=0.02):\n        pass\n", mod.__dict__)
    for v in vars(mod).values():
        if inspect.isfunction(v) or inspect.isclass(v):
            v.__module__ = mod.__name__
    got = violations([mod])
    assert got[0].startswith("sc3_jax.fake.C.m(action_space=") and got[1:] == ["sc3_jax.fake.C.m(tau=0.02)",
                                                                                 "sc3_jax.fake.f(data_fps=20.0)"]


# -- (b) a saved model records its robot facts; a rollout reads them --------------------------------------------
def test_a_saved_model_records_its_robot_facts_and_a_rollout_reads_them(tmp_path):
    import json

    import jax

    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout, rollout_io
    from sc3_jax.core.config import load_config, replace
    from sc3_jax.data import synthetic
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.data.norm_stats import NormStats
    from sc3_jax.data.shape import shape_from_dataset
    from sc3_jax.core.errors import UserError
    from sc3_jax.model import dit
    from sc3_jax.model.tokenizer import make_tokenizer

    store_dir = tmp_path / "episodes"
    synthetic.generate(store_dir, 2, length=24, seed=0)
    store = EpisodeStore(store_dir)
    info = json.loads((store_dir / "dataset.json").read_text())
    base = replace(load_config("tiny"), data=dict(path=str(store_dir)))
    assert base.data.fps is None  # no config states a frame rate: the data does
    cfg = shape_from_dataset(base, store)  # what `sc3 train` does
    assert cfg.data.fps == info["fps"] and cfg.data.state_dim == (store.state_dim or 0)
    stats = NormStats.from_store(store)
    tok = make_tokenizer(cfg.model)
    params = dit.init_params(cfg.model, tok.token_dim, jax.random.key(0), tok.grid(cfg.data.image_size))
    out = checkpoint.save(tmp_path / "model", cfg, stats, params)

    robot = checkpoint.read_robot(out)
    assert robot.fps == info["fps"] and robot.views == tuple(info["views"])
    assert robot.action_space == store.action_space and robot.action_dim == cfg.model.action_dim
    assert robot.state_dim == (store.state_dim or 0)
    assert rollout_io.data_fps(str(out), None) == info["fps"]  # `sc3 rollout` without --data-fps

    # the store moved away: the saved model still knows its facts (config.json + norm_stats.json)
    store_dir.rename(tmp_path / "moved")
    ro = rollout.Rollout(*checkpoint.load(out)[:2], data_fps=robot.fps, num_chunks=1)
    assert ro.spec.data_fps == info["fps"] and ro.spec.action_space == store.action_space
    assert ro.spec.stride == round(info["fps"] / cfg.rollout.control_hz) and ro.tau == math.inf

    # a model saved before config.json recorded its frame rate: read from its store, else one line naming the fix
    raw = json.loads((out / "config.json").read_text())
    del raw["data"]["fps"], raw["data"]["state_dim"]
    (out / "config.json").write_text(json.dumps(raw))
    with pytest.raises(UserError, match=r'no data\.fps .* add "fps": N') as e:
        checkpoint.read_robot(out)
    assert len(str(e.value).splitlines()) == 1
    (tmp_path / "moved").rename(store_dir)
    assert checkpoint.read_robot(out).fps == info["fps"]

    # a damaged fact is one line naming it, whatever the store says
    for field, bad in (("fps", "abc"), ("fps", -1), ("fps", 1e308), ("fps", True), ("state_dim", 2.5),
                       ("state_dim", -3), ("state_dim", "14"), ("state_dim", False)):
        damaged = {**raw, "data": {**raw["data"], "fps": info["fps"], "state_dim": 0, field: bad}}
        (out / "config.json").write_text(json.dumps(damaged))
        with pytest.raises(UserError, match=rf"data\.{field} is") as e:
            checkpoint.read_robot(out)
        assert len(str(e.value).splitlines()) == 1
