"""What a sweep costs on this machine, today's path against the new default, on the same rollouts in one run:

    nice python bench/sweep.py [--real-seeds 6] [--chunks 3] [--batch 6]

* real: the same real rollouts (two zoo policies, one per task, ``--real-seeds`` evaluation seeds each; MuJoCo at
  64x64, perception scoring) in one process with every rollout also read degraded (today) and in one worker process
  per core (``evaluate.engine``), with and without the degraded readings: the new default reads them on the
  calibration conditions only (``SweepConfig.degradations``), so its cost is the two weighted by that share.
  Steady state: seconds per rollout after each worker's first one, so the workers' start (a spawned interpreter
  importing JAX and compiling, paid once per sweep) is left out; the start is printed.
* online: the same batch of ``--batch`` initial conditions of one zoo policy inside the shipped world model, the
  first ``--chunks`` chunks (every chunk costs the same: static shapes), with today's sampler (8 forward Euler
  steps, 2 inverse re-read steps) in one process and the new default's (``SweepConfig``'s ``sample_steps`` /
  ``inverse_steps``) in one single-threaded worker process per core (``evaluate.engine``), each running the
  batch at the same time; each timed on its second call (compiled), scaled to a 12 s rollout.

full_protocol_h: the full protocol (13 policies; 36 evaluation + 6 calibration + 36 ceiling real rollouts and 36 +
6 online rollouts per policy) at these per-rollout costs. Last line:
``sweep_cost: real_s=<new s per real rollout> online_s=<new s per online rollout> full_protocol_h=<new> speedup=<today
/ new full protocol>``.

``--engines OLD [NEW]``: README command 1 (``sc3 sweep bench``, plus any flags after ``--``) end to end, run by the
code of git revision OLD and by NEW (default HEAD) at the same time (the machine's drift falls on both alike), each
from a ``git archive`` of its revision into a fresh store, the machine otherwise idle: the wall time of each, their
ratio, whether their records and report tables agree to the digit, NEW's report tables, and the share of NEW's wall
time its processes spent inside the world model's compiled calls (``timing.json``); ``--keep DIR`` keeps both
stores. The one engine (b499b6c) against the bussing engine before it:

    python bench/sweep.py --engines b499b6c^ HEAD     # 46 min on 2 cores (both sweeps at once)
    nice python bench/sweep.py --engines b499b6c^ HEAD -- --episodes 2 --calibration-episodes 0 --ceiling-episodes 0

Last line: ``engines: old_s=<s> new_s=<s> new_over_old=<ratio> records_equal=<bool> tables_equal=<bool>
compiled_share=<share>``.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import gzip
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FULL = {"policies": 13, "real": 36 + 6 + 36, "online": 36 + 6, "calibration": 6}  # the full protocol (docs/sweep.md)


def real_cost(workers: int, n_seeds: int, root: str, degrade: bool) -> tuple[float, float]:
    """(steady seconds per real rollout, seconds until the first records) for ``workers`` processes, with or without
    the perception scorer's reading of degraded copies."""
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    from sc3_jax.benchmarks.bussing.source import BussingSource
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig, _zoo_names
    from sc3_jax.benchmarks.bussing.zoo import ZOO
    from sc3_jax.evaluation import engine
    specs = [next(n for n in _zoo_names() if ZOO[n].task == t) for t in ("bussing", "reverse")]
    policies = engine.resolve_policies(specs, named_policy, need_task=True)
    jobs = [engine.Job(p.spec, p.name, "real", "evaluation", (10_000_000 + i,), degraded=degrade) for p in policies
            for i in range(n_seeds)]
    make_source = functools.partial(BussingSource, {p.name: p.task for p in policies}, (64, 64),
                                    str(perception.DEFAULT_WEIGHTS), 240, 2)
    setup = engine.Setup(root, None, SweepConfig(), make_source, named_policy)
    source = make_source()
    t0, arrivals = time.perf_counter(), []
    for _ in engine.run_jobs(jobs, setup, workers, lambda: engine.Runner(setup, {p.spec: p.policy for p in policies},
                                                                         source), model=False):
        arrivals.append(time.perf_counter() - t0)
    source.close()
    w = max(workers, 1)  # each worker's first rollout includes its start (and its first compile)
    return (arrivals[-1] - arrivals[w - 1]) / (len(arrivals) - w), arrivals[w - 1]


def online_cost(fd: int, inv: int, chunks: int, batch: int, barrier=None) -> float:
    """Seconds per 12 s online rollout of one process (amortised over the batch) at (forward, inverse) Euler steps;
    with ``barrier``, the timed call starts when every worker beside this one has compiled."""
    import jax

    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout
    from sc3_jax.core.config import replace
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing.source import initial_observation
    from sc3_jax.benchmarks.bussing.sweep import SHIPPED_WORLD_MODEL, STATE_READER_FILE
    from sc3_jax.benchmarks.bussing.policy_eval import make_env
    from sc3_jax.benchmarks.bussing.tasks import task_id
    from sc3_jax.benchmarks.bussing.zoo import load_policy
    cfg, stats, params = checkpoint.load(str(SHIPPED_WORLD_MODEL))
    cfg = replace(cfg, sample=dict(steps=fd, inverse_steps=inv), rollout=dict(episode_seconds=12.0))
    fps = checkpoint.read_robot(SHIPPED_WORLD_MODEL, cfg).fps  # its data's frame rate, as the sweep reads it
    full_chunks = rollout.make_spec(cfg, fps, action_space=stats.action_space).num_chunks
    reader = perception.state_reader(perception.load(str(SHIPPED_WORLD_MODEL / STATE_READER_FILE)))
    ro = rollout.Rollout(cfg, stats, data_fps=fps, state_reader=reader, num_chunks=chunks)
    env = make_env((64, 64))
    obs = [initial_observation(env, 10_000_000 + i, "bussing") for i in range(batch)]
    env.close()
    frames = np.stack([np.repeat(f[:, None], ro.spec.context, 1) for f, _ in obs])
    ics = rollout.InitialConditions(frames, np.stack([p for _, p in obs]), np.full(batch, task_id("bussing")))
    keys = np.asarray(rollout.episode_keys(0, batch))
    policy = load_policy("bus_bc_full")
    ro.run(params, policy, ics, keys, math.inf)  # compile
    if barrier is not None:
        barrier.wait(timeout=1800)
    t0 = time.perf_counter()
    jax.block_until_ready(ro.run(params, policy, ics, keys, math.inf)["u"])
    return (time.perf_counter() - t0) / chunks * full_chunks / batch


_BARRIER = None  # a bench worker's (set by _init_worker)


def _init_worker(barrier) -> None:
    global _BARRIER
    import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
    _BARRIER = barrier


def _online_in_worker(args) -> float:
    return online_cost(*args, barrier=_BARRIER)


def online_cost_workers(fd: int, inv: int, chunks: int, batch: int, workers: int) -> float:
    """Seconds per online rollout of ``workers`` sweep worker processes (``evaluate.worker_pool``: one thread each)
    running a batch each at the same time: the slowest one's time over every rollout they ran."""
    import multiprocessing as mp

    from sc3_jax.evaluation import worker_pool
    barrier = mp.get_context("spawn").Barrier(workers)
    with worker_pool.pool(workers, _init_worker, (barrier,)) as pool:
        times = pool.map(_online_in_worker, [(fd, inv, chunks, batch)] * workers, chunksize=1)
    return max(times) / workers


def hours(real_s: float, online_s: float) -> float:
    return FULL["policies"] * (FULL["real"] * real_s + FULL["online"] * online_s) / 3600


def start_revision(rev: str, work: Path, flags: list[str]) -> tuple[subprocess.Popen, float, Path]:
    """README command 1 by the code of git revision ``rev`` (its ``sc3_jax`` and ``configs``, laid out as the
    installed package is) into ``work/store``, started: (the process, its start time, the store)."""
    code, store = work / "code", work / "store"
    code.mkdir(parents=True)
    repo = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "archive", rev, "sc3_jax", "configs"], check=True, capture_output=True,
                             cwd=repo).stdout
    subprocess.run(["tar", "-x", "-C", str(code)], input=archive, check=True)
    (code / "configs").rename(code / "sc3_jax" / "configs")  # the wheel's layout: sc3_jax.configs
    env = {**os.environ, "PYTHONPATH": str(code)}  # ahead of the editable install's finder
    log = open(work / "sweep.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "sc3_jax.cli", "sweep", "bench", "--out", str(store),
                             "--no-progress", *flags], env=env, cwd=work, stdout=log, stderr=subprocess.STDOUT)
    return proc, time.perf_counter(), store


def records(store: Path) -> dict:
    """The store's records by id (results.jsonl, or its .gz)."""
    path = store / "results.jsonl"
    lines = (path.read_text() if path.is_file() else gzip.decompress((store / "results.jsonl.gz").read_bytes())
             .decode()).splitlines()
    return {r["id"]: r for r in map(json.loads, filter(None, lines))}


def tables(store: Path) -> list[str]:
    """The report's table rows (report.md lines that start with ``|``)."""
    return [line for line in (store / "report" / "report.md").read_text().splitlines() if line.startswith("|")]


def engines(old: str, new: str, flags: list[str], keep: str | None = None) -> None:
    """Both revisions' sweeps at the same time, so that the machine's own drift (40% within the hour on the 2-core
    machine, docs/results.md#sweep-cost) falls on both alike."""
    kept = contextlib.nullcontext(tempfile.mkdtemp(prefix="engines_", dir=keep)) if keep else None
    with kept or tempfile.TemporaryDirectory() as d:
        runs = {name: start_revision(rev, Path(d) / name, flags) for name, rev in (("old", old), ("new", new))}
        wall = {}
        while len(wall) < len(runs):
            for name, (proc, t0, _) in runs.items():
                if name not in wall and proc.poll() is not None:
                    if proc.returncode:
                        sys.exit(f"the {name} revision's sweep failed (exit {proc.returncode}): "
                                 f"{(Path(d) / name / 'sweep.log').read_text()[-2000:]}")
                    wall[name] = time.perf_counter() - t0
            time.sleep(1)
        old_store, new_store = runs["old"][2], runs["new"][2]
        same_records = records(old_store) == records(new_store)
        same_tables = tables(old_store) == tables(new_store)
        timing = json.loads((new_store / "timing.json").read_text())
        share = timing.get("share_in_world_model_calls", float("nan"))
        for line in tables(new_store):
            print(line)
    print(f"| engine | revision | wall s (both at once) |\n|---|---|---|\n| old | {old} | {wall['old']:.0f} |\n"
          f"| new | {new} | {wall['new']:.0f} |")
    print(f"(new: {timing['seconds_in_world_model_calls']:.0f} s inside the world model's compiled calls over "
          f"{timing['model_workers']} processes, {share:.1%} of their wall time)" if "seconds_in_world_model_calls"
          in timing else "(new: its timing.json has no compiled-call time)")
    print(f"engines: old_s={wall['old']:.0f} new_s={wall['new']:.0f} new_over_old={wall['new'] / wall['old']:.3f} "
          f"records_equal={same_records} tables_equal={same_tables} compiled_share={share:.3f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real-seeds", type=int, default=6, help="real rollouts per policy (two policies)")
    ap.add_argument("--chunks", type=int, default=3, help="online chunks timed (scaled to a 12 s rollout)")
    ap.add_argument("--batch", type=int, default=6)
    ap.add_argument("--engines", nargs="+", metavar="REV", help="OLD [NEW]: README command 1 by two revisions' "
                    "code; flags after -- go to sc3 sweep bench")
    ap.add_argument("--keep", metavar="DIR", help="with --engines: keep both stores (and their logs) in a new "
                    "folder under DIR")
    argv = sys.argv[1:] if argv is None else list(argv)
    flags = argv[argv.index("--") + 1:] if "--" in argv else []
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if a.engines:
        if len(a.engines) > 2:
            ap.error("--engines takes OLD [NEW]")
        return engines(a.engines[0], a.engines[1] if len(a.engines) == 2 else "HEAD", flags, a.keep)
    import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
    from sc3_jax.evaluation.engine import default_workers
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig
    new = SweepConfig()
    workers = new.workers or default_workers()
    with tempfile.TemporaryDirectory() as d1, tempfile.TemporaryDirectory() as d2:
        real_old, start_old = real_cost(1, a.real_seeds, d1, True)
        real_clean, start_new = real_cost(workers, a.real_seeds, d2, False)
    with tempfile.TemporaryDirectory() as d3:
        real_degraded, _ = real_cost(workers, a.real_seeds, d3, True)
    # the new default reads degraded copies of the calibration conditions' real rollouts only
    share = {"all": 1.0, "none": 0.0, "calibration": FULL["calibration"] / FULL["real"]}[new.degradations]
    real_new = share * real_degraded + (1 - share) * real_clean
    online_old = online_cost(8, 2, a.chunks, a.batch)
    from sc3_jax.evaluation.engine import in_workers
    steps = (new.sample_steps or 8, new.inverse_steps or 8, a.chunks, a.batch)
    online_new = online_cost_workers(*steps, workers) if in_workers(workers, workers) else online_cost(*steps)
    online_one = online_cost(*steps)  # the new sampler in one process on every core: what the workers add
    h_old, h_new = hours(real_old, online_old), hours(real_new, online_new)
    print("| path | real s / rollout | online s / rollout | full protocol h |\n|---|---|---|---|")
    print(f"| today: 1 process, 8 + 2 Euler steps | {real_old:.2f} | {online_old:.1f} | {h_old:.2f} |")
    print(f"(real, {workers} workers: {real_clean:.2f} s clean, {real_degraded:.2f} s also read degraded)")
    print(f"| new default: {workers} worker processes (one thread each), degraded copies read on {new.degradations}, "
          f"{new.sample_steps} + {new.inverse_steps} Euler steps | "
          f"{real_new:.2f} | {online_new:.1f} | {h_new:.2f} |")
    print(f"(online at {steps[0]} + {steps[1]} steps: {online_one:.1f} s in one process, {online_new:.1f} s in "
          f"{workers} worker processes: {online_one / online_new:.2f}x)")
    print(f"(until the first real records: {start_old:.1f} s in process, {start_new:.1f} s with {workers} workers)")
    print(f"sweep_cost: real_s={real_new:.2f} online_s={online_new:.1f} full_protocol_h={h_new:.2f} "
          f"speedup={h_old / h_new:.2f}")


if __name__ == "__main__":
    main()
