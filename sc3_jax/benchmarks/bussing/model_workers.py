"""A sweep's world-model batches (offline replay, closed loop): one batch scored (``ModelRunner``), and many in
worker processes when the world model runs on the CPU.

Why processes: one process spreads each DiT matmul over every core, but 2 threads run it only 1.69x as fast as 1
on the 2-core machine. Single-threaded processes (``worker_pool``), each running whole batches, keep every core
busy: 2 workers ran 0.86-1.18x the online rollouts per hour of one process on both cores (four bench runs, the
machine's noise included; docs/sweep.md). Each
worker loads the world model, scorer and policies once, runs whole batches (a sweep's ``Unit`` and mode), writes
their arrays into the store itself and returns their records; the parent appends them in job order. A batch's
values depend only on its initial conditions and episode keys, so records do not depend on the number of workers
(tests/test_sweep_shards.py). On an accelerator the batches run in the sweep's own process, on the device.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np

from sc3_jax.evaluate import worker_pool
from sc3_jax.evaluate.results import ResultsStore, rollout_id


@dataclasses.dataclass(frozen=True)
class ModelJob:
    spec: str  # the policy as the sweep was given it (policies/resolve.py spelling), re-resolved in a worker
    name: str
    task: str
    mode: str  # "offline" or "online"
    seeds: tuple[int, ...]
    start: int  # episode-key index of the first seed (its block's offset + its place in the block)


@dataclasses.dataclass(frozen=True)
class ModelSetup:
    """What every worker needs, picklable: the store, the sweep's settings (SweepConfig) and its scorer weights."""
    store: str
    sweep: object  # SweepConfig, with state_reader resolved
    perception: str  # weights of the perception scorer


class ModelRunner:
    """World model, simulator (for initial observations), scorer and resolved policies of one process."""

    def __init__(self, setup: ModelSetup, policies: dict | None = None, env=None, scorer=None):
        import jax

        from sc3_jax import checkpoint, sharding
        from sc3_jax import rollout as ro_mod
        from sc3_jax.config import MeshConfig
        from sc3_jax.benchmarks.bussing import perception
        from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
        from sc3_jax.evaluate.world_model_defaults import evaluation_config
        from sc3_jax.benchmarks.bussing.policy_eval import make_env
        cfg = setup.sweep
        wcfg, stats, self.params = checkpoint.load(cfg.world_model)
        wcfg = evaluation_config(wcfg, cfg)  # the one set of evaluation settings (sc3 rollout / diagnose too)
        p_params = perception.load(setup.perception)
        reader = perception.load(cfg.state_reader) if cfg.state_reader else p_params
        # a shard's batches run on its own process's devices: under jax.distributed every process runs a different
        # share, so a mesh over every host's devices would wait for programs the other processes never start
        mesh = sharding.make_mesh(MeshConfig(-1, 1, 1), jax.local_devices())
        self.ro = ro_mod.Rollout(wcfg, stats, mesh=mesh, data_fps=checkpoint.read_robot(cfg.world_model, wcfg).fps,
                                 state_reader=perception.state_reader(reader))
        self.setup, self.policies = setup, dict(policies or {})
        self.env = env or make_env(tuple(self.ro.spec.image_size))
        self.scorer = scorer or PerceptionScorer(p_params)
        self.store = ResultsStore(setup.store)

    def __call__(self, job: ModelJob) -> list[dict]:
        if job.spec not in self.policies:
            from sc3_jax.benchmarks.bussing.hooks import named_policy
            from sc3_jax.policies.resolve import resolve
            self.policies[job.spec] = resolve(job.spec, named=named_policy).policy
        return run_batch(job, self.ro, self.params, self.env, self.policies[job.spec], self.setup.sweep.rollout_seed,
                         self.store, self.scorer)


def initial_observation(env, seed: int, task: str):
    """Frames uint8 [V, H, W, 3] and end-effector pose [7] right after reset: where real and imagined start."""
    env.reset(seed, task)
    f = env.render()
    return np.stack([f[v] for v in env.views]), env.ee_pose().astype(np.float32)


def run_batch(job: ModelJob, ro, params, env, policy, rollout_seed: int, store: ResultsStore, scorer) -> list[dict]:
    """Offline or online rollouts of one batch of initial conditions -> one record per rollout (arrays written)."""
    from sc3_jax import rollout as ro_mod
    from sc3_jax.evaluate.metrics import psnr_by_view
    from sc3_jax.policies.base import JaxPolicy
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition, task_id
    s, name, seeds = ro.spec, job.name, job.seeds
    obs = [initial_observation(env, seed, job.task) for seed in seeds]
    frames0 = np.stack([np.repeat(f[:, None], s.context, 1) for f, _ in obs])  # [B, V, K, H, W, 3]: at rest
    ics = ro_mod.InitialConditions(frames0, np.stack([p for _, p in obs]), np.full(len(seeds), task_id(job.task)))
    # episode i's noise depends only on (rollout_seed, i): every policy meets the same draws (common random numbers)
    keys = np.asarray(ro_mod.episode_keys(rollout_seed, len(seeds), start=job.start))
    if job.mode == "offline":
        real = [store.load_arrays(rollout_id(name, seed, "real")) for seed in seeds]
        actions = np.stack([ro_mod.chunk_actions(r["actions"], s) for r in real])
        out = ro.run_offline(params, ics, actions, keys, math.inf)
    else:
        try:
            out = (ro.run if isinstance(policy, JaxPolicy) else ro.run_host)(params, policy, ics, keys, math.inf)
        except Exception as e:  # the policy's code (or its server): its traceback, and which policy and rollouts
            e.add_note(f"while policy {name!r} ({job.spec}) acted in {job.mode} rollouts "
                       f"{rollout_id(name, seeds[0], job.mode)} .. {rollout_id(name, seeds[-1], job.mode)}")
            raise
    recs = []
    for b, seed in enumerate(seeds):
        ic = make_initial_condition(seed, job.task)
        frames = np.concatenate([out["initial_frames"][b][:, -1:], out["frames"][b]], 1)  # [V, 1 + N*l, ...]
        cuts = scorer.score_cuts(frames, ic.objects, ic.destinations(), s.keep, s.num_chunks, prefix=1)
        rec = {"objects": cuts[-1], "u": out["u"][b].tolist(), "u_raw": out["u_raw"][b].tolist(),
               "num_chunks": s.num_chunks, "frames_per_chunk": s.keep, "stride": s.stride}
        if job.mode == "online":
            rec["objects_by_cut"] = cuts
        else:
            targets, valid = ro_mod.recorded_targets(real[b]["frames"], s)
            rec["psnr_view"] = psnr_by_view(out["frames"][b], targets, valid)[1].tolist()  # per view
        store.save_arrays(rollout_id(name, seed, job.mode), frames=frames, actions=out["actions"][b],
                          reread=out["reread"][b], u=out["u"][b], u_raw=out["u_raw"][b])
        recs.append(rec)
    return recs


def in_workers(workers: int, n_jobs: int) -> bool:
    """Whether the batches run in worker processes: several workers and jobs, and the world model on the CPU."""
    import jax
    return workers > 1 and n_jobs > 1 and jax.default_backend() == "cpu"


_RUNNER: ModelRunner | None = None  # the worker process's own (set once by _init; never used in the parent)


def _init(setup: ModelSetup) -> None:
    global _RUNNER
    import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
    _RUNNER = ModelRunner(setup)


def _work(job: ModelJob) -> list[dict]:
    return _RUNNER(job)


def run_model_jobs(jobs: list[ModelJob], setup: ModelSetup, workers: int, runner=None
                   ) -> Iterator[tuple[ModelJob, list[dict]]]:
    """(job, records) for every job, in job order, each rollout's arrays already in the store: in ``workers``
    single-threaded processes when :func:`in_workers`, else in this process by ``runner()`` (a callable building
    this process's ModelRunner, called only if needed)."""
    if not jobs:
        return
    if not in_workers(workers, len(jobs)):
        run = runner()
        for job in jobs:
            yield job, run(job)
        return
    with worker_pool.pool(min(workers, len(jobs)), _init, (setup,)) as pool:
        yield from zip(jobs, pool.imap(_work, jobs, chunksize=1))
