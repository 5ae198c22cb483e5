"""A toy benchmark defined outside the package, named as ``toy_benchmark:BENCHMARK`` (tests/ is on the path): no file
of sc3_jax names it, and ``sc3 sweep`` / ``sc3 report`` / ``sc3 diagnose`` use it through the registry alone.

Its "robot" is test_any_robot.py's bimanual one (14-D absolute joint targets); its sweep is the core engine's
(``evaluation/ic_sweep.py``) on held-out episodes, with a toy real-outcome table (``real.csv``) and the held-out
episodes' own frames kept as the real frames of the report's objects-kept row; its scene measure is the fraction of
bright pixels; its scorer returns ``{criterion: bool}`` from the imagined state; its policies are named ``hold`` and
``reach`` (an offset from the state they observe)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from sc3_jax.evaluation.benchmark import Benchmark
from sc3_jax.evaluation.world_model_defaults import SamplerSteps

CALLS = {"scene": 0, "scorer": 0, "named": []}  # what the commands called, for the test to check
OFFSETS = {"hold": 0.0, "reach": 0.3}
REAL = {"hold": [False, False], "reach": [True, True]}  # the toy's real outcomes, per policy and held-out episode


@dataclasses.dataclass(frozen=True, kw_only=True)
class ToySweepConfig(SamplerSteps):
    """The toy benchmark's sweep: its policies inside the world model from held-out episodes."""

    world_model: str
    """the world model"""
    data: str
    """held-out episodes, one initial condition each"""
    out: str
    """the results store"""
    policies: tuple[str, ...] = tuple(OFFSETS)
    """the toy's policy names"""
    episodes: int = 2
    """initial conditions per policy"""
    episode_seconds: float = 1.2
    """horizon of the imagined rollouts"""
    batch: int = 2
    """initial conditions per world-model call"""


class Offset:
    """Absolute joint targets a fixed offset from the observed state, for every step of the chunk."""

    def __init__(self, d: float, chunk: int = 8, dim: int = 14):
        self.d, self.chunk, self.action_dim = d, chunk, dim

    def infer(self, obs):
        return np.repeat(np.asarray(obs["state"])[None, :self.action_dim] + self.d, self.chunk, 0).astype(np.float32)


def named_policy(name: str):
    CALLS["named"].append(name)
    if name not in OFFSETS:
        raise ValueError(f"unknown toy policy {name!r}: {sorted(OFFSETS)}")
    return Offset(OFFSETS[name]), None


def score(view) -> dict[str, bool]:
    """Moved far on average (success) and at all, from the imagined state."""
    CALLS["scorer"] += 1
    moved = float(np.mean(view.state[-1] - view.state[0]))
    return {"success": moved > 0.2, "moved": bool(moved > 0.05)}


def bright(frames: np.ndarray) -> np.ndarray:
    """The toy scene measure: the fraction of bright pixels, frames uint8 [V, T, H, W, 3] -> [V, T]."""
    CALLS["scene"] += 1
    return (np.asarray(frames, np.float32).mean(-1) > 127).mean((-2, -1))


def dark(frames: np.ndarray) -> np.ndarray:
    return (np.asarray(frames, np.float32).mean(-1) < 64).mean((-2, -1))


def run_sweep(cfg: ToySweepConfig) -> Path:
    from sc3_jax.core import atomic
    from sc3_jax.model import checkpoint
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.evaluation import ic_sweep
    from sc3_jax.measures import permanence
    from sc3_jax.evaluation.report_episodes import REAL_FRAMES

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    store = EpisodeStore(cfg.data)
    ids = store.episode_ids()[:cfg.episodes]
    atomic.write_text(out / "real.csv", "policy,episode,success\n" + "".join(
        f"{p},{e},{str(REAL[p][i]).lower()}\n" for p in cfg.policies for i, e in enumerate(ids)))
    ic = ic_sweep.ICSweepConfig(
        initial_conditions=cfg.data, world_model=cfg.world_model, policies=cfg.policies, scorer="toy_benchmark:score",
        out=cfg.out, episodes=cfg.episodes, calibration_episodes=0, real=(str(out / "real.csv"),),
        sample_steps=cfg.sample_steps, inverse_steps=cfg.inverse_steps, episode_seconds=cfg.episode_seconds,
        taus=(math.inf,), batch=cfg.batch, progress=False)
    root = ic_sweep.run(ic, named=named_policy)
    # the held-out episodes' frames at the report's times (model steps after the last context frame), as the
    # "real" side of the objects-kept row
    wcfg = checkpoint.read_config(cfg.world_model)
    hz, stride = wcfg.rollout.control_hz, int(round(store.fps / wcfg.rollout.control_hz))
    at = np.array(sorted(set(permanence.times(hz).values())), np.int64)
    for e in ids:
        ep = store.load(e)
        last = (wcfg.data.context_frames - 1) * stride
        idx = np.minimum(last + stride * at, ep.length - 1)
        frames = np.stack([np.asarray(ep.frames[v])[idx] for v in wcfg.data.views])
        for p in cfg.policies:
            atomic.save_npz(out / REAL_FRAMES / p / f"{e}.npz", frames=frames, at=at, hz=np.float64(hz))
    return root


BENCHMARK = Benchmark(name="toy", sweep_config=ToySweepConfig, run_sweep=run_sweep,
                      measures={"objects": bright, "dark": dark}, named_policy=named_policy)
NOT_ONE = object()  # a module:attr that is no Benchmark
