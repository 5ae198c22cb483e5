"""Episodes in the SO-101 simulator: of a controller (``run_episode``), of a policy (``run_policy_episode``), and many
of either in worker processes (``run_episodes``).

Per step ``t`` an episode records what was observed before action ``t`` (frame, ``agent_pos`` state,
``environment_state``), the action (clipped, as applied) and whether the task was done after it (``success[t]``,
LeRobot's ``next.success``). It ends when the simulator ends it (success, or the block out of the workspace) -- the
terminating step is recorded -- or after ``max_steps``.

A policy gets ``{"images": uint8 [V, H, W, 3] (the env's views), "state": float32 [14] (agent_pos), "task": int32 0}`` and returns a
chunk float32 [chunk, 4] of raw actions; the first ``execute`` are applied, then it observes again. A JaxPolicy's rng
is ``fold_in(key(0), seed)`` (split once per chunk), so an episode depends only on (policy, seed).

Workers: spawned single-threaded processes (``evaluation/worker_pool``), each with its own simulator, running whole
episodes; results come back in job order, and an episode depends only on its job (the simulator resets every state
with the seed), so results do not depend on the number of workers.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator

import numpy as np

from .env import ACTION_HIGH, ACTION_LOW, VIEWS, So101Env

MAX_STEPS = 150  # 15 s at 10 Hz: the clean controller needs ~5 s
EXECUTE = 10  # actions of a policy's chunk applied before it observes again: 1 s
HOLD = np.array([0.0, 0.0, 0.0, 1.0], np.float32)  # stay, gripper open


@dataclasses.dataclass
class EpisodeRecord:
    seed: int
    frames: np.ndarray | None  # uint8 [T, V, H, W, 3], the env's views (None: not recorded)
    actions: np.ndarray  # float32 [T, 4]
    states: np.ndarray  # float32 [T, 14] agent_pos
    env_state: np.ndarray  # float32 [T, 6] block xyz, goal xyz
    success: np.ndarray  # bool [T]: done after action t
    succeeded: bool
    steps: int
    source: str = ""  # what acted (a recipe or policy name)


def run_episode(env: So101Env, act_fn: Callable, seed: int, max_steps: int = MAX_STEPS, record: bool = True,
                source: str = "", hold: int = 0) -> EpisodeRecord:
    """One episode from ``seed``. ``act_fn(env, obs) -> action [4]``; its ``reset(seed)``, if it has one, is called
    after the simulator's. ``hold``: steps of ``HOLD`` applied after the reset, before the episode (not recorded):
    the sweep's initial conditions are the reset frame and the frame after one such step (``sweep.py``)."""
    obs = env.reset(seed)
    for _ in range(hold):
        obs, _, _ = env.step(HOLD)
    if hasattr(act_fn, "reset"):
        act_fn.reset(seed)
    frames, actions, states, env_state, success = [], [], [], [], []
    for _ in range(max_steps):
        if record:
            frames.append(env.render_views())
        states.append(obs["agent_pos"])
        env_state.append(obs["environment_state"])
        a = np.asarray(act_fn(env, obs), np.float32).reshape(-1)
        if a.shape != (4,):
            raise ValueError(f"an SO-101 action is 4-D (dx, dy, dz, gripper), got {a.shape[0]}-D")
        a = np.clip(a, ACTION_LOW, ACTION_HIGH)  # what the step applies
        actions.append(a)
        obs, ok, done = env.step(a)
        success.append(ok)
        if done:
            break
    return EpisodeRecord(int(seed), np.stack(frames) if record else None, np.stack(actions).astype(np.float32),
                         np.stack(states).astype(np.float32), np.stack(env_state).astype(np.float32),
                         np.array(success, bool), bool(any(success)), len(actions), source)


class PolicyActor:
    """A policy (JaxPolicy or host policy) as ``act_fn``: observes every ``execute`` steps, applies its chunk."""

    def __init__(self, policy, execute: int = EXECUTE):
        from sc3_jax.policies.base import JaxPolicy, as_host

        self.host = as_host(policy) if isinstance(policy, JaxPolicy) else policy
        self.execute = int(execute)
        self.chunk, self.k = None, 0

    def reset(self, seed: int) -> None:
        import jax

        from sc3_jax.policies.base import JaxAsHost

        if isinstance(self.host, JaxAsHost):
            # the policy's draws come from a key of this initial condition: an episode's result does not depend on
            # which episodes ran before it with the same host
            self.host._rng = jax.random.fold_in(jax.random.key(0), int(seed))
        elif hasattr(self.host, "reset"):  # e.g. a LeRobot policy: its action queue and history
            self.host.reset()
        self.chunk, self.k = None, 0

    def __call__(self, env: So101Env, obs: dict) -> np.ndarray:
        if self.chunk is None or self.k >= min(self.execute, len(self.chunk)):
            p = {"images": env.render_views(), "state": np.asarray(obs["agent_pos"], np.float32),
                 "task": np.int32(0)}
            self.chunk, self.k = np.asarray(self.host.infer(p), np.float32), 0
            if self.chunk.ndim != 2 or self.chunk.shape[1] != env.action_dim or not len(self.chunk):
                raise ValueError(f"a policy returns a chunk [chunk, {env.action_dim}], got {list(self.chunk.shape)}")
        a = self.chunk[self.k]
        self.k += 1
        return a


def run_policy_episode(env: So101Env, policy, seed: int, execute: int = EXECUTE, max_steps: int = MAX_STEPS,
                       record: bool = True, source: str = "") -> EpisodeRecord:
    """Closed-loop episode of ``policy`` (a JaxPolicy, jitted here, or a host policy with ``infer``) from ``seed``.
    Several episodes of one JaxPolicy: pass a ``PolicyActor`` to ``run_episode`` (jitted once)."""
    actor = policy if isinstance(policy, PolicyActor) else PolicyActor(policy, execute)
    return run_episode(env, actor, seed, max_steps, record, source)


# -- many episodes in worker processes -----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Job:
    """One episode: simulator ``seed`` and what acts, a controller recipe (``controllers.RECIPES``; its draws
    seeded by ``controller_seed``) or a policy spec (``policies/resolve.py``: an SO-101 zoo name,
    ``package.module:attr`` ...)."""

    seed: int
    recipe: str | None = None
    policy: str | None = None
    controller_seed: int = 0


@dataclasses.dataclass(frozen=True)
class Setup:
    """What every worker needs (picklable)."""

    image_size: tuple[int, int] = (80, 80)
    views: tuple[str, ...] = VIEWS
    max_steps: int = MAX_STEPS
    execute: int = EXECUTE
    record: bool = True
    hold: int = 0  # steps of HOLD before each episode (run_episode)


def default_workers() -> int:
    """One worker per core this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class _Runner:
    """A simulator and the resolved policies of one process."""

    def __init__(self, setup: Setup):
        self.setup, self.env, self.actors = setup, So101Env(setup.image_size, views=setup.views), {}

    def __call__(self, job: Job) -> EpisodeRecord:
        s = self.setup
        if (job.recipe is None) == (job.policy is None):
            raise ValueError(f"job {job}: give a recipe or a policy")
        if job.recipe is not None:
            from .controllers import RECIPE_BY_NAME
            ctl = RECIPE_BY_NAME[job.recipe].controller(job.controller_seed)
            return run_episode(self.env, ctl, job.seed, s.max_steps, s.record, job.recipe, s.hold)
        if job.policy not in self.actors:
            from sc3_jax.policies.resolve import resolve

            from .zoo import named_policy
            self.actors[job.policy] = PolicyActor(resolve(job.policy, named=named_policy).policy, s.execute)
        try:
            return run_episode(self.env, self.actors[job.policy], job.seed, s.max_steps, s.record, job.policy,
                               s.hold)
        except Exception as e:  # the policy's code: its traceback, and which policy and episode
            e.add_note(f"while policy {job.policy!r} acted in the SO-101 episode of seed {job.seed}")
            raise

    def close(self) -> None:
        self.env.close()


_RUNNER: _Runner | None = None  # a worker process's own (set once by _init; never used in the parent)


def _init(setup: Setup) -> None:
    global _RUNNER
    import sc3_jax.benchmarks.so101  # noqa: F401  (picks the GL backend before mujoco is imported)
    _RUNNER = _Runner(setup)  # its GL context goes with the process (a pool worker runs no exit handlers)


def _work(job: Job) -> EpisodeRecord:
    return _RUNNER(job)


def run_episodes(jobs: list[Job], setup: Setup = Setup(), workers: int = 1) -> Iterator[EpisodeRecord]:
    """The record of every job, in job order. ``workers`` <= 1 runs them in this process."""
    if not jobs:
        return
    if workers <= 1 or len(jobs) == 1:
        runner = _Runner(setup)
        try:
            for job in jobs:
                yield runner(job)
        finally:
            runner.close()
        return
    from sc3_jax.evaluation import worker_pool

    with worker_pool.pool(min(workers, len(jobs)), _init, (setup,)) as pool:
        yield from pool.imap(_work, jobs, chunksize=1)
