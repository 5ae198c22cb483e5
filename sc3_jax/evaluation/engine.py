"""The sweep engine: every sweep's closed loop, for a simulated benchmark and a lab's held-out episodes alike.

A sweep is policies x initial conditions, in up to three modes, into one results store (``results.py``):

    real     the policy acts in the benchmark's simulator (a :class:`Source` with ``real``)
    offline  the world model replays the store's real rollout's actions open loop from the same first frame; PSNR
             against the real frames
    online   the policy acts inside the world model (closed loop, ``rollout.Rollout``), untruncated (tau = inf),
             U_chunk per chunk; the outcomes of the rollout cut after each chunk a candidate tau could cut it at

The engine owns what every sweep does the same way: the work units (:func:`work_units`: a policy's initial
conditions of one block in batches, fixed sets, so records do not depend on where a sweep was killed, how many
workers ran it or which shard), their episode keys (condition i's sampling noise depends only on (rollout_seed, its
block's offset + i): every policy meets the same draws), JAX policies inside the scan and host policies between
jitted chunk steps, the frames a scorer reads (the last context frame, then the kept ones), per-cut scoring, the
records and arrays, skipping what the store holds, worker processes (:func:`run_jobs`), progress and timing.

A benchmark supplies only what only it knows, as a :class:`Source` (built in every process that rolls out): its
initial conditions, its real rollouts (where it has a simulator), its outcome scorer and the fields its records
carry (e.g. a task and its split, or a held-out episode's id and its block). The sweeps of the benchmarks
(``benchmarks/NAME/``) and of held-out episodes (``ic_sweep.py``) build their work and their Source and hand both here.

``sweep.json`` also records what the rollouts came from (:func:`with_identity`): the world model's content hash and
training step, and the content hash of the scorer and of each policy where they are files. Resuming against a changed
one is refused in one line naming both.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import worker_pool
from sc3_jax.evaluation.results import ResultsStore, check_policy_names, rollout_id, terminated_at


# ================================================================================================================
# Work units and shards
# ================================================================================================================
@dataclasses.dataclass(frozen=True)
class Unit:
    """One share of a sweep's work: a batch of initial conditions of one policy and what runs on them (its real
    rollouts, and the world-model modes of its block, with the block's episode-key offset). Batches are fixed sets,
    so a unit's records do not depend on which process or shard runs it."""
    policy: int
    block: str
    start: int  # index of the first condition within its block
    seeds: tuple[int, ...]  # the conditions: simulator seeds, or held-out episodes' indices
    real: bool
    modes: tuple[tuple[str, int], ...]  # (world-model mode, fold-in offset of its episode keys)


# the simulated benchmarks' world-model modes per block and each block's episode-key offset (blocks never share noise)
SEED_BLOCKS = {"evaluation": (("offline", 0), ("online", 0)), "calibration": (("online", 1 << 20),), "ceiling": ()}


def work_units(n_policies: int, blocks: dict[str, list[int]], modes, batch: int,
               block_modes: dict[str, tuple[tuple[str, int], ...]] = SEED_BLOCKS) -> list[Unit]:
    """Every unit of a sweep, in the order one process runs them (shard I of N takes units I, I + N, ...):
    per policy and block (``blocks``: name -> its conditions), batches of ``batch`` conditions running the real mode
    (if in ``modes``) and the block's world-model modes of ``block_modes`` that ``modes`` names."""
    units = []
    for p in range(n_policies):
        for block, seeds in blocks.items():
            wm = tuple((m, off) for m, off in block_modes[block] if m in modes)
            if not wm and "real" not in modes:
                continue
            for g in range(0, len(seeds), batch):
                units.append(Unit(p, block, g, tuple(seeds[g:g + batch]), "real" in modes, wm))
    return units


def parse_shard(shard: str | None) -> tuple[int, int]:
    """"I/N" -> (I, N); None -> (0, 1)."""
    if shard is None:
        return 0, 1
    try:
        i, n = (int(x) for x in shard.split("/"))
    except ValueError:
        i, n = -1, 0
    if not 0 <= i < n:
        raise UserError(f"--shard {shard!r}: expected I/N with 0 <= I < N, e.g. 0/4")
    return i, n


def shard_of(shard: str | None) -> str | None:
    """A sweep's shard: ``shard``, else this process's share under ``jax.distributed``, else None (all of it)."""
    if shard is not None:
        parse_shard(shard)
        return shard
    import jax
    return f"{jax.process_index()}/{jax.process_count()}" if jax.process_count() > 1 else None


def shard_dir(out: str | Path, shard: str | None) -> Path:
    """Where a shard's store lives: OUT/shard-I-of-N (OUT itself when unsharded)."""
    if shard is None:
        return Path(out)
    i, n = parse_shard(shard)
    return Path(out) / f"shard-{i}-of-{n}"


# ================================================================================================================
# Policies: one resolution for every sweep
# ================================================================================================================
@dataclasses.dataclass(frozen=True)
class Policy:
    """A sweep's policy: as it was given (``spec``, re-resolved in a worker), its record name, its task (None:
    none given and none of its own) and the resolved policy."""
    spec: str
    name: str
    task: str | None
    policy: Any


def resolve_policies(specs, named=None, *, need_task: bool = False, tasks=(), mappings: dict | None = None,
                     **kw) -> list[Policy]:
    """Each ``policies/resolve.py`` spelling of ``specs`` resolved (``named``: a benchmark's own policy names;
    ``mappings``: policy name -> the openpi observation mapping its ``ws://`` server speaks; ``kw``: ``resolve``'s
    chunk, action_space, num_views), their names unique and fit for the store's directories
    (``check_policy_names``); with ``need_task`` each must have a task (of ``tasks``, the benchmark's). A spelling
    that does not resolve is a one-line UserError naming it."""
    from sc3_jax.policies.resolve import parse, resolve

    out = []
    for spec in specs:
        try:
            name, body, task = parse(spec)
            if need_task and task is not None and tasks and task not in tasks:  # before a server is connected to
                raise UserError(f"policy {spec!r}: the sweep has no task {task!r}; expected NAME=SPEC@TASK (e.g. "
                                f"NAME=ws://HOST:PORT@TASK) with TASK in {list(tasks)}")
            r = resolve(spec, family=(mappings or {}).get(name or body), named=named, **kw)
        except UserError:
            raise
        except (ValueError, TypeError, ImportError, AttributeError, ConnectionError, KeyError,
                FileNotFoundError) as e:
            raise UserError(f"--policies {spec!r}: {e}") from None
        if need_task and (r.task is None or (tasks and r.task not in tasks)):
            why = "needs its task" if r.task is None else f"has no task {r.task!r}"
            raise UserError(f"policy {spec!r}: the sweep {why}; expected NAME=SPEC@TASK (e.g. "
                            f"NAME=ws://HOST:PORT@TASK) with TASK in {list(tasks)}")
        out.append(Policy(spec, r.name, r.task, r.policy))
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"--policies: the name(s) {dup} occur twice; name each as NAME=SPEC")
    check_policy_names(names)
    return out


# ================================================================================================================
# What a benchmark supplies
# ================================================================================================================
@dataclasses.dataclass(frozen=True)
class Job:
    """One batch the engine runs: conditions ``seeds`` of one policy's block in one mode (a real job: one seed)."""
    spec: str
    name: str
    mode: str  # "real", "offline" or "online"
    block: str
    seeds: tuple[int, ...]
    start: int = 0  # episode-key index of the first condition (its block's offset + its place in the block)
    degraded: bool = False  # real: also score degraded copies of its frames (the scorer's robustness check)

    def ids(self) -> list[str]:
        return [rollout_id(self.name, s, self.mode) for s in self.seeds]


class Source(Protocol):
    """What a benchmark hands the engine, in every process that rolls out."""

    outcomes: str
    """the record field of a rollout's outcomes: e.g. "objects" (one outcome per object) or "outcomes"
    ({criterion: bool}); the outcomes of each cut go to FIELD_by_cut"""
    every_cut: bool
    """score the rollout cut after every chunk (a list over cuts 0..N; a report may then try any tau), or only where
    a candidate tau cuts it (a dict "cut" -> outcomes)"""
    keeps: tuple[str, ...]
    """rollout arrays the store keeps beside frames, actions, u and u_raw (e.g. "reread", "states")"""

    def fields(self, job: Job, seed: int) -> dict:
        """The record fields of a condition beside the engine's (e.g. its task and split; its episode and block)."""

    def conditions(self, job: Job, spec):
        """The ``rollout.InitialConditions`` of ``job.seeds``, as ``job``'s policy sees them, for a world model of
        rollout ``spec`` (``rollout.RolloutSpec``: its context frames, views, image size)."""

    def score(self, job: Job, b: int, frames: np.ndarray, states: np.ndarray, cuts: list[int], keep: int
              ) -> dict[int, Any]:
        """The outcomes of rollout ``b`` of ``job`` cut after each of ``cuts`` chunks: ``frames`` [V, 1 + N*l, H, W,
        3] (the last context frame, then the ``keep`` = l kept frames of each chunk; a cut after c chunks keeps the
        first 1 + c*l), ``states`` [1 + N*l, S] what the policy saw of the robot's state."""

    def real(self, job: Job, policy) -> tuple[dict, dict]:
        """(record fields, arrays) of the real rollout of ``job`` (one seed) in the benchmark's simulator; a Source
        without a simulator has none, and its sweeps no real mode."""


@dataclasses.dataclass(frozen=True)
class Setup:
    """What every process of a sweep needs, picklable (a worker builds its :class:`Runner` from it)."""
    store: str
    world_model: str | None  # None: no world-model mode
    sampler: Any  # the sweep's config (a ``world_model_defaults.Sampler``: sampler steps, taus, batch, rollout_seed)
    source: Callable[[], Source] | None = None  # builds a worker's Source (None: the sweep runs in its own process)
    named: Callable | None = None  # the benchmark's own policy names (``policies.resolve``'s ``named``)
    state_reader: Callable[[], Any] | None = None  # builds the world model's state reader (``rollout.Rollout``)
    learned_state: bool = False  # hand the policies the world model's learned robot state (``state_head.npz``)
    pad: bool = False  # pad every batch to ``sampler.batch`` conditions: one compiled shape


def mesh_for(batch: int):
    """A mesh over as many local devices as divide the batch: every device busy, no batch padded beyond it. Local:
    under jax.distributed every process runs a different share, so a mesh over every host's devices would wait for
    programs the other processes never start."""
    import jax

    from sc3_jax.model import sharding
    from sc3_jax.core.config import MeshConfig

    devices = jax.local_devices()
    d = max(k for k in range(1, min(batch, len(devices)) + 1) if batch % k == 0)
    return sharding.make_mesh(MeshConfig(-1, 1, 1), devices[:d])


def load_world_model(setup: Setup, state_reader=None):
    """(rollout.Rollout, params) of ``setup.world_model`` under the sweep's evaluation settings."""
    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout, state_head
    from sc3_jax.evaluation.world_model_defaults import evaluation_config

    wcfg, stats, params = checkpoint.load(setup.world_model)
    wcfg = evaluation_config(wcfg, setup.sampler)  # the one set of evaluation settings (sc3 rollout / diagnose too)
    ro = rollout.Rollout(wcfg, stats, mesh=mesh_for(setup.sampler.batch),
                         data_fps=checkpoint.read_robot(setup.world_model, wcfg).fps,
                         state_reader=state_reader,
                         head=state_head.load(setup.world_model) if setup.learned_state else None)
    return ro, params


def cut(u: np.ndarray, tau: float) -> int:
    """Chunks a rollout with U_chunk ``u`` [N] keeps under threshold ``tau``: those before the first with U > tau
    (``calibrate.cut``'s rule, which the report applies to the stored ``u`` / ``u_raw``)."""
    first = int(terminated_at(np.asarray(u)[None], tau)[0])
    return len(u) if first < 0 else first


# ================================================================================================================
# One process's rollouts
# ================================================================================================================
class Runner:
    """World model, source and resolved policies of one process: ``runner(job)`` runs a job, writes its arrays
    into the store and returns its records (without the fields the parent adds: id, mode, seed, policy and the
    source's own, :func:`run`)."""

    def __init__(self, setup: Setup, policies: dict | None = None, source: Source | None = None, model=None):
        self.setup, self.policies = setup, dict(policies or {})
        self._source, self._model = source, model
        self.store = ResultsStore(setup.store)

    @property
    def source(self) -> Source:
        if self._source is None:
            self._source = self.setup.source()
        return self._source

    @property
    def model(self):
        if self._model is None:
            reader = self.setup.state_reader() if self.setup.state_reader else None
            self._model = load_world_model(self.setup, reader)
        return self._model

    def policy(self, job: Job):
        if job.spec not in self.policies:
            from sc3_jax.policies.resolve import resolve
            self.policies[job.spec] = resolve(job.spec, named=self.setup.named).policy
        return self.policies[job.spec]

    def __call__(self, job: Job) -> list[dict]:
        return self.real(job) if job.mode == "real" else self.batch(job)

    def compiled_seconds(self) -> float:
        """Seconds this process has spent inside the world model's jitted programs (``Rollout.compiled_seconds``)."""
        return self._model[0].compiled_seconds if self._model is not None else 0.0

    def real(self, job: Job) -> list[dict]:
        rid = job.ids()[0]
        try:
            rec, arrays = self.source.real(job, self.policy(job))
        except Exception as e:  # the policy's code: its traceback, and which policy and rollout
            e.add_note(f"while policy {job.name!r} ({job.spec}) acted in real rollout {rid}")
            raise
        self.store.save_arrays(rid, **arrays)
        return [rec]

    def batch(self, job: Job) -> list[dict]:
        """Offline or online rollouts of one batch of conditions -> one record per rollout (arrays written)."""
        from sc3_jax.rollout import rollout
        from sc3_jax.policies.base import JaxPolicy

        ro, params = self.model
        s, source, seeds, rids = ro.spec, self.source, job.seeds, job.ids()
        ics = source.conditions(job, s)
        n = len(seeds)
        size = max(self.setup.sampler.batch, n) if self.setup.pad else n
        if size > n:  # one shape for every batch: one compile
            ics = ics.take(np.asarray(list(range(n)) + [n - 1] * (size - n)))
        keys = np.asarray(rollout.episode_keys(self.setup.sampler.rollout_seed, size, start=job.start))
        policy = self.policy(job)
        try:
            if job.mode == "offline":  # the store's real rollouts' actions, replayed
                real = [self.store.load_arrays(rollout_id(job.name, seed, "real")) for seed in seeds]
                actions = np.stack([rollout.chunk_actions(r["actions"], s) for r in real])
                out = ro.run_offline(params, ics, actions, keys, math.inf)
            elif isinstance(policy, JaxPolicy):
                out = ro.run(params, policy, ics, keys, math.inf)
            else:
                out = ro.run_host(params, policy, ics, keys, math.inf)
        except UserError as e:  # e.g. a host policy's chunks, checked as they arrive
            raise UserError(f"--policies {job.spec}: {e} (world model {self.setup.world_model})") from None
        except Exception as e:  # the policy's code (or its server): its traceback, and which policy and rollouts
            e.add_note(f"while policy {job.name!r} ({job.spec}) acted in {job.mode} rollouts {rids[0]} .. {rids[-1]}")
            raise
        taus = [float(t) for t in self.setup.sampler.taus] + [math.inf]
        raw = self.setup.sampler.tau_units != "normalised"
        learned = "robot_states" in out  # what the policy saw: the learned robot state, else the commanded one
        recs = []
        for b, (seed, rid) in enumerate(zip(seeds, rids)):
            frames = np.concatenate([out["initial_frames"][b][:, -1:], out["frames"][b]], 1)  # [V, 1 + N*l, ...]
            states = np.concatenate([np.asarray((ics.robot if learned else ics.state)[b], np.float32)[None],
                                     out["robot_states" if learned else "states"][b]], 0)
            u, u_raw = out["u"][b], out["u_raw"][b]
            if job.mode == "offline":
                cuts = [s.num_chunks]
            elif source.every_cut:
                cuts = list(range(s.num_chunks + 1))
            else:
                cuts = sorted({cut(u_raw if raw else u, t) for t in taus})
            by_cut = source.score(job, b, frames, states, cuts, s.keep)
            rec = {source.outcomes: by_cut[s.num_chunks]}
            if job.mode == "online":
                rec[f"{source.outcomes}_by_cut"] = [by_cut[c] for c in cuts] if source.every_cut else \
                    {str(c): by_cut[c] for c in cuts}
            rec.update(u=u.tolist(), u_raw=u_raw.tolist(), num_chunks=s.num_chunks, frames_per_chunk=s.keep,
                       stride=s.stride)
            if job.mode == "offline":
                from sc3_jax.measures.metrics import psnr_by_view
                targets, valid = rollout.recorded_targets(real[b]["frames"], s)
                rec["psnr_view"] = psnr_by_view(out["frames"][b], targets, valid)[1].tolist()  # per view
            kept = {"reread": out["reread"][b], "states": states[1:]}
            self.store.save_arrays(rid, frames=frames, actions=out["actions"][b],
                                   **{k: kept[k] for k in source.keeps}, u=u, u_raw=u_raw)
            recs.append(rec)
        return recs


def in_workers(workers: int, n_jobs: int, model: bool = True) -> bool:
    """Whether jobs run in worker processes: several workers and jobs, and (world-model jobs) the model on the CPU
    (on an accelerator the batches run in the sweep's own process, on the device)."""
    import jax
    return workers > 1 and n_jobs > 1 and (not model or jax.default_backend() == "cpu")


_RUNNER: Runner | None = None  # the worker process's own (set once by _init; never used in the parent)


def _init(setup: Setup) -> None:
    global _RUNNER
    _RUNNER = Runner(setup)


def _timed(run: Runner, job: Job) -> tuple[list[dict], float]:
    """``run(job)``'s records and the seconds it spent inside the world model's jitted programs."""
    before = run.compiled_seconds()
    recs = run(job)
    return recs, run.compiled_seconds() - before


def _work(job: Job) -> tuple[list[dict], float]:
    return _timed(_RUNNER, job)


def run_jobs(jobs: list[Job], setup: Setup, workers: int, runner: Callable[[], Runner], model: bool = True,
             clock: dict | None = None) -> Iterator[tuple[Job, list[dict]]]:
    """(job, records) for every job, in job order, each rollout's arrays already in the store: in ``workers``
    single-threaded processes when :func:`in_workers` (each builds its own Runner from ``setup``), else in this
    process by ``runner()`` (called only if needed).

    Why processes: one process spreads each matmul over every core, but 2 threads ran a DiT 1.69x as fast as 1 on
    the 2-core machine, and a simulator episode is single-threaded; single-threaded processes running whole jobs
    keep every core busy. Records do not depend on the number of workers (tests/test_sweep_shards.py).

    ``clock["compiled"]`` (if given) adds up the seconds every process spent inside the world model's jitted
    programs."""
    if not jobs:
        return
    clock = {} if clock is None else clock
    clock.setdefault("compiled", 0.0)
    if setup.source is None or not in_workers(workers, len(jobs), model):
        run = runner()
        for job in jobs:
            recs, seconds = _timed(run, job)
            clock["compiled"] += seconds
            yield job, recs
        return
    with worker_pool.pool(min(workers, len(jobs)), _init, (setup,)) as pool:
        for job, (recs, seconds) in zip(jobs, pool.imap(_work, jobs, chunksize=1)):
            clock["compiled"] += seconds
            yield job, recs


def environment() -> dict:
    """What a run's numbers depend on besides the code and the inputs: the numeric libraries' versions and the CPU.
    XLA's CPU numerics move with both in the last digits, and a simulator's contacts can amplify them into another
    trajectory, so two machines' records may differ where one machine's never do."""
    import importlib.metadata
    import platform
    out = {}
    for dist in ("jax", "jaxlib", "numpy", "mujoco"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:  # not Linux
        pass
    return {**out, "python": platform.python_version(), "cpu": cpu}


def default_workers() -> int:
    """One worker per core this process may use."""
    import os
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


# ================================================================================================================
# The sweep
# ================================================================================================================
def run(setup: Setup, config: dict, policies: list[Policy], units: list[Unit], *, source: Source,
        workers: int = 1, progress: bool = True, model=None, degraded: Callable[[str], bool] = lambda block: False,
        before: Callable[[ResultsStore], None] | None = None) -> Path:
    """Run (or resume) ``units`` of ``policies`` into the store ``setup.store`` (``config``: its sweep.json); returns
    the store's directory. ``source``: this process's (the workers build theirs from ``setup.source``); ``model``:
    this process's (rollout.Rollout, params), if built already; ``degraded(block)``: whether a block's real rollouts
    are also scored on degraded frames; ``before(store)``: called once the store is open and locked (e.g. to link
    another store's real rollouts in). Records: ``id``, ``mode``, ``seed``, ``policy``, the source's fields, then
    the rollout's (see the module docstring)."""
    import jax
    from tqdm import tqdm

    store = ResultsStore(setup.store, config, lock=True)
    in_process = {p.spec: p.policy for p in policies}
    runner_ = []

    def runner() -> Runner:  # this process's, with its resolved policies and source, built once if needed
        if not runner_:
            runner_.append(Runner(setup, in_process, source, model))
        return runner_[0]

    def head(job: Job, seed: int) -> dict:
        return {"id": rollout_id(job.name, seed, job.mode), "mode": job.mode, "seed": seed, "policy": job.name,
                **source.fields(job, seed)}
    try:
        if before is not None:
            before(store)
        done = store.done()
        total = sum(len(u.seeds) * (u.real + len(u.modes)) for u in units)
        bar = tqdm(total=total, initial=len(done), desc="sweep", unit="rollout", disable=not progress)
        timing = {"real": 0.0, "offline": 0.0, "online": 0.0}
        count = {"real": 0, "offline": 0, "online": 0}
        degrade = {s for u in units if degraded(u.block) for s in u.seeds}
        real = sorted({(u.policy, s) for u in units if u.real for s in u.seeds})
        blocks = {(u.policy, s): u.block for u in units for s in u.seeds}
        jobs = [Job(policies[p].spec, policies[p].name, "real", blocks[p, s], (s,), degraded=s in degrade)
                for p, s in real if rollout_id(policies[p].name, s, "real") not in done]
        t0 = time.time()
        for job, recs in run_jobs(jobs, setup, workers, runner, model=False):
            store.append([{**head(job, job.seeds[0]), **recs[0]}])
            bar.update(1)
        timing["real"], count["real"] = time.time() - t0, len(jobs)
        model_jobs = [Job(policies[u.policy].spec, policies[u.policy].name, mode, u.block, u.seeds, offset + u.start)
                      for u in units for mode, offset in u.modes
                      if not all(rollout_id(policies[u.policy].name, s, mode) in done for s in u.seeds)]
        t1, clock = time.time(), {}
        for job, recs in run_jobs(model_jobs, setup, workers, runner, clock=clock):
            store.append([{**head(job, s), **r} for s, r in zip(job.seeds, recs)])
            timing[job.mode] += time.time() - t1  # the workers overlap: each mode's share of the wall time
            count[job.mode] += len(recs)
            bar.update(len(recs))
            t1 = time.time()
        bar.close()
        for p in policies:  # our side of a connection (an openpi server's client)
            if callable(getattr(p.policy, "close", None)):
                p.policy.close()
        if callable(getattr(source, "close", None)):
            source.close()
        wall = time.time() - t0
        model_workers = workers if setup.source is not None and in_workers(workers, len(model_jobs)) else 1
        compiled = clock.get("compiled", 0.0)
        atomic.write_json(store.root / "timing.json", {
            "seconds_last_run": wall, "seconds_by_mode": timing, "rollouts_run": count,
            "workers": workers, "model_workers": model_workers,
            # summed over the processes that ran the world model; the share is of their wall time together
            "seconds_in_world_model_calls": compiled,
            "share_in_world_model_calls": compiled / (model_workers * wall) if wall > 0 else 0.0,
            "devices": [str(d) for d in jax.local_devices()], "environment": environment()})
        return store.root
    finally:
        store.close()  # the lock: another sweep may take the store


# ================================================================================================================
# What the rollouts came from
# ================================================================================================================
IDENTITY_KEYS = ("world_model_sha256", "world_model_step", "scorer_sha256", "policies_sha256")


def identity(world_model: str | None, scorer: str | None, policies: list[tuple[str, str]]) -> dict:
    """The identity fields of a sweep's ``sweep.json``: the world model's content hash and step
    (``checkpoint.identity``; none when ``world_model`` is None, a sweep that reads no model), the ``scorer``
    spec's hash and each (name, spec) of ``policies`` whose spec names files (:func:`spec_sha256`)."""
    from sc3_jax.model import checkpoint

    out = {}
    if world_model is not None:
        wm = checkpoint.identity(world_model)
        out.update(world_model_sha256=wm["sha256"], world_model_step=wm["step"])
    scored = spec_sha256(scorer) if scorer else None
    if scored:
        out["scorer_sha256"] = scored
    acting = {name: spec_sha256(spec) for name, spec in policies}
    if any(acting.values()):
        out["policies_sha256"] = {n: h for n, h in acting.items() if h}
    return out


def spec_sha256(spec: str) -> str | None:
    """The content hash of the files a --scorer / --policies spec names: a ``package.module:attr``'s source file, a
    ``detector:DIR`` or ``lerobot:PATH`` directory; None for a server, a built-in or a benchmark's own name (those
    are not files of the user's, or not files at all)."""
    import importlib.util

    from sc3_jax.model import checkpoint
    from sc3_jax.policies.resolve import parse

    try:
        body = parse(spec)[1]
    except ValueError:
        return None
    for prefix in ("detector:", "lerobot:"):
        if body.startswith(prefix):
            root = Path(body[len(prefix):])
            files = [root] if root.is_file() else sorted(f for f in root.rglob("*") if f.is_file())
            return checkpoint.files_sha256([(str(f.relative_to(root)) if f != root else f.name, f) for f in files]) \
                if files else None
    if "://" in body or ":" not in body:
        return None
    try:  # imported already (the spec was resolved): its module's file
        found = importlib.util.find_spec(body.partition(":")[0])
    except (ImportError, ValueError):
        return None
    origin = Path(found.origin) if found is not None and found.origin else None
    return checkpoint.files_sha256([(origin.name, origin)]) if origin is not None and origin.is_file() else None


def with_identity(out: str | Path, config: dict, ident: dict) -> dict:
    """``config`` (a sweep.json to be) with the identity fields ``ident`` (:func:`identity`), after checking them
    against the store ``out`` already holds: a resume against another world model (its workdir trained on, or
    another export at the same path), scorer or policy file is refused in one line naming the old and the new.
    A store whose rollouts were recorded before sweep.json named their model is accepted with a note and
    ``config`` returned as it is: it records nothing new (nothing says what its first rollouts came from)."""
    path = Path(out) / "sweep.json"
    if not path.is_file() or not ResultsStore(out)._holds_results():  # a new store (or one with no rollout yet)
        return {**config, **ident}
    old = atomic.read_json(path, "restore it from a copy, or use another --out")
    if not isinstance(old, dict):
        return {**config, **ident}  # not a sweep's record: the store refuses it in its own line
    if "world_model_sha256" not in old:
        print(f"note: {path} predates recording the world model's content hash: resumed as it was, with none "
              "recorded (a changed model at the same path is not detected; a new --out records it)")
        return config

    def model(d):
        step, sha = d.get("world_model_step"), str(d.get("world_model_sha256"))[:16]
        return f"sha256 {sha}, an export" if step is None else f"step {step}, sha256 {sha}"
    if ident.get("world_model_sha256") not in (None, old["world_model_sha256"]):
        raise UserError(f"{out} holds rollouts of world model {old.get('world_model')} ({model(old)}); "
                        f"{config.get('world_model')} is now {model(ident)}: resuming would rank two models' rollouts "
                        "together; give the model it was swept with, or use another --out")
    if old.get("scorer_sha256") != ident.get("scorer_sha256"):
        raise UserError(f"{out} was scored by --scorer {old.get('scorer')} with sha256 "
                        f"{str(old.get('scorer_sha256'))[:16]}; its files are now sha256 "
                        f"{str(ident.get('scorer_sha256'))[:16]}: resuming would mix two scorers' outcomes; restore "
                        "it, or use another --out")
    was, now = old.get("policies_sha256") or {}, ident.get("policies_sha256") or {}
    changed = sorted(n for n in set(was) & set(now) if was[n] != now[n])
    if changed:
        n = changed[0]
        raise UserError(f"{out} holds rollouts of policy {n!r} with sha256 {was[n][:16]}; its files are now sha256 "
                        f"{now[n][:16]}: resuming would rank two versions of it together; restore it, name the new "
                        "one otherwise, or use another --out")
    return {**config, **ident}
