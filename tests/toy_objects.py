"""A second toy benchmark defined outside the package, named as ``toy_objects:BENCHMARK`` (tests/ is on the path), with
what the simulated benchmark has and the first toy lacks: a simulator of its own (real rollouts in the sweep's store),
per-object criteria and two splits. No file of sc3_jax names it; it runs through the one sweep engine
(``evaluation/engine.py``), the report of a simulated benchmark and its tau calibration.

Its "robot" is test_any_robot.py's bimanual one (14-D absolute joint targets). Its objects are the two arms, each
scored on two ordered criteria, ``reached`` (moved > 0.1 on average) then ``held`` (> 0.25), from the robot's state
(the real one in its simulator, the imagined one inside the world model). Its two tasks belong to two splits,
``seen`` (in distribution, listed first: tau is chosen there) and ``novel``. Its initial conditions are the held-out
episodes of ``--data`` (seed i: episode i modulo their number); its simulator moves each joint halfway to the
commanded target every step."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from sc3_jax.evaluation.benchmark import Benchmark
from sc3_jax.evaluation.world_model_defaults import Sampler

ARMS = {"left": slice(0, 7), "right": slice(7, 14)}  # its objects
CRITERIA = {"reached": 0.1, "held": 0.25}  # ordered, cumulative: mean joint displacement of an arm above each
SPLITS = {"tidy": "seen", "swap": "novel"}  # task -> split, in distribution first
POLICIES = {  # name -> (task, offset per call of the left arm, of the right arm)
    "calm_tidy": ("tidy", 0.01, 0.04), "eager_tidy": ("tidy", 0.09, 0.05),
    "calm_swap": ("swap", 0.03, 0.0), "eager_swap": ("swap", 0.12, 0.1)}


@dataclasses.dataclass(frozen=True, kw_only=True)
class ObjectsSweepConfig(Sampler):
    """The per-object toy's sweep: its policies in its simulator and inside the world model, then the report."""

    world_model: str
    """the world model"""
    data: str
    """held-out episodes: the initial conditions"""
    out: str
    """the results store"""
    policies: tuple[str, ...] = tuple(POLICIES)
    """the toy's policy names"""
    episodes: int = 3
    """evaluation conditions per policy"""
    seed0: int = 0
    """first evaluation seed"""
    calibration_episodes: int = 2
    """conditions per policy that choose tau"""
    calibration_seed0: int = 100
    """first calibration seed"""
    ceiling_episodes: int = 2
    """a second real set per policy (the noise ceiling)"""
    ceiling_seed0: int = 200
    """first ceiling seed"""
    modes: tuple[str, ...] = ("real", "online")
    """what runs"""
    episode_seconds: float | None = 1.2
    """horizon of both rollouts"""
    taus: tuple[float, ...] = (math.inf, 1.0, 0.3, 0.1)
    """candidate U_chunk thresholds"""
    batch: int = 2
    """conditions per world-model call"""
    progress: bool = False
    """progress bar"""


class Offset:
    """Absolute joint targets: the observed state plus a fixed offset per arm, for every step of the chunk."""

    def __init__(self, left: float, right: float, chunk: int = 8, dim: int = 14):
        self.d = np.r_[np.full(7, left), np.full(7, right)].astype(np.float32)
        self.chunk, self.action_dim = chunk, dim

    def infer(self, obs):
        return np.repeat((np.asarray(obs["state"], np.float32)[:self.action_dim] + self.d)[None], self.chunk, 0)


def named_policy(name: str):
    if name not in POLICIES:
        raise ValueError(f"unknown toy policy {name!r}: {sorted(POLICIES)}")
    task, left, right = POLICIES[name]
    return Offset(left, right), task


def outcomes(states: np.ndarray) -> list[dict]:
    """One outcome per arm from the robot's states [T, 14]: its criteria in their order, and its category."""
    from sc3_jax.measures.metrics import outcome_category

    out = []
    for arm, sl in ARMS.items():
        moved = float(np.mean(states[-1, sl] - states[0, sl]))
        passed = {c: moved > low for c, low in CRITERIA.items()}
        out.append({"object": arm, **passed, "outcome": outcome_category(passed)})
    return out


class ObjectsSource:
    """What the toy hands the engine (``engine.Source``)."""

    outcomes = "objects"
    every_cut = True
    keeps = ("states",)

    def __init__(self, cfg: ObjectsSweepConfig, tasks: dict[str, str]):
        self.cfg, self.tasks, self._ics = cfg, tasks, None

    def _conditions(self, spec):
        if self._ics is None:
            from sc3_jax.model import checkpoint
            from sc3_jax.rollout import rollout_io
            wcfg = checkpoint.read_config(self.cfg.world_model)
            self._ics = rollout_io.load_initial_conditions(self.cfg.data, wcfg, spec, None, 0, 0)[1]
        return self._ics

    def fields(self, job, seed: int) -> dict:
        task = self.tasks[job.name]
        return {"task": task, "split": SPLITS[task]}

    def conditions(self, job, spec):
        ics = self._conditions(spec)
        picked = ics.take(np.asarray([s % len(ics.frames) for s in job.seeds]))
        return picked._replace(task=np.full(len(job.seeds), list(SPLITS).index(self.tasks[job.name]), np.int32))

    def score(self, job, b: int, frames, states, cuts, keep: int) -> dict:
        return {c: outcomes(states[:1 + c * keep]) for c in cuts}

    def real(self, job, policy) -> tuple[dict, dict]:
        """The toy simulator: every step each joint moves halfway to its commanded target; the policy is asked for a
        chunk every ``keep`` steps (as inside the world model). Frames: the condition's last context frame, at the
        data's rate."""
        from sc3_jax.model import checkpoint
        from sc3_jax.rollout import rollout
        from sc3_jax.evaluation.world_model_defaults import evaluation_config
        wcfg = evaluation_config(checkpoint.read_config(self.cfg.world_model), self.cfg)  # the sweep's horizon
        fps = checkpoint.read_robot(self.cfg.world_model, wcfg).fps
        spec = rollout.make_spec(wcfg, fps, action_space=checkpoint.read_norm_stats(self.cfg.world_model).action_space)
        ic = self.conditions(job, spec)
        state, states, actions = np.asarray(ic.state[0], np.float32), [], []
        for t in range(spec.num_chunks * spec.keep):
            if t % spec.keep == 0:
                chunk = policy.infer({"state": state})
            a = chunk[t % spec.keep]
            states.append(state)
            actions.append(a)
            state = state + 0.5 * (a - state)
        states.append(state)
        states = np.stack(states)
        scored = outcomes(states)
        frames = np.repeat(np.asarray(ic.frames[0])[:, -1:], len(states) * spec.stride, 1)
        return ({"objects": scored, "perception": outcomes(states), "length": len(states), "score_stride": 1},
                {"frames": frames, "actions": np.stack(actions), "states": states})


def run_sweep(cfg: ObjectsSweepConfig) -> Path:
    from sc3_jax.evaluation import engine
    from sc3_jax.evaluation.results import seed_blocks

    policies = engine.resolve_policies(cfg.policies, named_policy, need_task=True, tasks=tuple(SPLITS))
    tasks = {p.name: p.task for p in policies}
    config = json.loads(json.dumps({**dataclasses.asdict(cfg), "taus": [str(t) for t in cfg.taus],
                                    "splits": list(dict.fromkeys(SPLITS.values())), "criteria": list(CRITERIA)}))
    setup = engine.Setup(cfg.out, cfg.world_model, cfg, named=named_policy)
    units = engine.work_units(len(policies), seed_blocks(cfg), cfg.modes, cfg.batch)
    return engine.run(setup, config, policies, units, source=ObjectsSource(cfg, tasks), progress=cfg.progress)


def bright(frames: np.ndarray) -> np.ndarray:
    """The toy's scene measure: the fraction of bright pixels, frames uint8 [V, T, H, W, 3] -> [V, T]."""
    return (np.asarray(frames, np.float32).mean(-1) > 127).mean((-2, -1))


BENCHMARK = Benchmark(name="toy_objects", sweep_config=ObjectsSweepConfig, run_sweep=run_sweep,
                      measures={"objects": bright}, named_policy=named_policy)
