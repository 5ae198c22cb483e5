"""Real (simulated) rollouts of a sweep: one rollout scored (``run_real``), and many in worker processes.

A real rollout is a single-threaded MuJoCo episode plus a small perception network: one process leaves the other
cores idle. Each worker is a spawned, single-threaded process (``worker_pool``) that builds its own simulator,
scorer and policies once, runs whole rollouts, writes each rollout's arrays into the store itself (atomically, one
file per rollout) and returns its record. The parent appends the records in job order (``imap``), so a store's lines
and values do not depend on the number of workers: a rollout depends only on its (policy, seed)
(``sim/policy_eval.run_policy_episode`` seeds the policy from the simulator seed) and every worker computes it with
the same code and the same compiled shapes.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator

import numpy as np

from sc3_jax.evaluate import worker_pool
from sc3_jax.evaluate.results import ResultsStore, rollout_id


@dataclasses.dataclass(frozen=True)
class RealJob:
    spec: str  # the policy as the sweep was given it (policies/resolve.py spelling), re-resolved in the worker
    name: str
    task: str
    seed: int
    degradations: bool = False  # also score the frames' degraded copies (SweepConfig.degradations)


@dataclasses.dataclass(frozen=True)
class RealSetup:
    """What every worker needs, picklable: the store to write into and how rollouts are run and scored."""
    store: str
    image_size: tuple[int, int]
    perception: str  # weights of the perception scorer
    max_steps: int
    score_stride: int


def default_workers() -> int:
    """One worker per core this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class _Runner:
    """Simulator, scorer and resolved policies of one process (the parent's when ``workers == 1``)."""

    def __init__(self, setup: RealSetup, policies: dict | None = None, env=None, scorer=None):
        from sc3_jax.benchmarks.bussing import perception
        from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
        from sc3_jax.benchmarks.bussing.policy_eval import make_env
        self.setup, self.policies = setup, dict(policies or {})
        self.env = env or make_env(setup.image_size)
        self.scorer = scorer or PerceptionScorer(perception.load(setup.perception))
        self.store = ResultsStore(setup.store)

    def __call__(self, job: RealJob) -> dict:
        if job.spec not in self.policies:
            from sc3_jax.benchmarks.bussing.hooks import named_policy
            from sc3_jax.policies.resolve import resolve
            self.policies[job.spec] = resolve(job.spec, named=named_policy).policy
        s = self.setup
        rid = rollout_id(job.name, job.seed, "real")
        try:
            rec, arrays = run_real(self.env, job.name, job.task, self.policies[job.spec], job.seed, self.scorer,
                                   s.max_steps, s.score_stride, job.degradations)
        except Exception as e:  # the policy's code: its traceback, and which policy and rollout
            e.add_note(f"while policy {job.name!r} ({job.spec}) acted in real rollout {rid}")
            raise
        self.store.save_arrays(rid, **arrays)
        return rec


def run_real(env, name, task, policy, seed, scorer, max_steps: int, score_stride: int,
             degradations: bool = False) -> tuple[dict, dict]:
    """One simulated rollout, scored by physics and by perception (on every ``score_stride``-th frame and the last:
    the world model's frame rate, so real and imagined rollouts are read alike); with ``degradations`` also by
    perception on degraded copies of the frames (``degrade.py``: how the scorer reads generated-looking frames)."""
    from sc3_jax.evaluate.scorers import RolloutView
    from sc3_jax.benchmarks.bussing.scorers import SimScorer
    from sc3_jax.benchmarks.bussing.policy_eval import run_policy_episode
    r = run_policy_episode(env, policy, seed, task, record=True, max_steps=max_steps)
    frames = np.stack([r.frames[v] for v in env.views])  # [V, T, H, W, 3] at 20 Hz
    view = RolloutView(rollout_id(name, seed, "real"), frames, r.ic.objects, r.ic.destinations(),
                       [o.to_json() for o in r.outcomes])
    clean, degraded = scorer.score_real(view, seed, score_stride, degradations)
    rec = {"objects": SimScorer().score(view), "perception": clean, "length": int(r.length), "prompt": r.ic.prompt,
           "score_stride": score_stride}
    if degradations:
        rec["perception_degraded"] = degraded
    return rec, {"frames": frames, "actions": r.actions.astype(np.float32), "ee_pose": r.ee_pose.astype(np.float32),
                 "object_pos": r.object_pos}


_RUNNER: _Runner | None = None  # the worker process's own (set once by _init; never used in the parent)


def _init(setup: RealSetup) -> None:
    global _RUNNER
    import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
    _RUNNER = _Runner(setup)


def _work(job: RealJob) -> dict:
    return _RUNNER(job)


def run_real_jobs(jobs: list[RealJob], setup: RealSetup, workers: int, policies: dict, env, scorer
                  ) -> Iterator[tuple[RealJob, dict]]:
    """(job, record) for every job, in job order, each rollout's arrays already in the store. ``workers`` <= 1 runs
    them in this process, with its ``policies`` (spec -> resolved policy), ``env`` and ``scorer``."""
    if not jobs:
        return
    if workers <= 1 or len(jobs) == 1:
        runner = _Runner(setup, policies, env, scorer)
        for job in jobs:
            yield job, runner(job)
        return
    with worker_pool.pool(min(workers, len(jobs)), _init, (setup,)) as pool:
        yield from zip(jobs, pool.imap(_work, jobs, chunksize=1))
