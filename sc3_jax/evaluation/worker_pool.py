"""The sweep engine's worker processes (``engine.run_jobs``): spawned, on the CPU, one thread each.

*Spawned*: forking a process that has started JAX's thread pools is unsafe. *On the CPU*: on an accelerator machine the
workers must not claim its memory. *One thread each*: the processes are the parallelism; a worker's XLA spreading its
ops over every core beside the other workers only adds contention (2 real workers on the 2-core machine: 0.92 s per
rollout single-threaded, 1.10 s not; 2 world-model workers: 0.86-1.18x the online rollouts per hour of one process on
both cores, in four bench runs). XLA's single-threaded CPU kernels give the multi-threaded ones' bits, so records do not
depend on it (tests/test_sweep_shards.py compares worker processes with one process).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal

SINGLE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"  # added to XLA_FLAGS


def pool(processes: int, initializer, initargs: tuple):
    """A spawn-context ``multiprocessing.Pool`` whose workers run JAX on one CPU thread each."""
    ctx = mp.get_context("spawn")
    saved = {k: os.environ.get(k) for k in ("JAX_PLATFORMS", "XLA_FLAGS")}  # a spawned process copies os.environ
    os.environ["JAX_PLATFORMS"] = "cpu"
    os.environ["XLA_FLAGS"] = f"{saved['XLA_FLAGS'] or ''} {SINGLE_THREAD}".strip()
    try:
        return ctx.Pool(processes, initializer=_deaf_to_ctrl_c, initargs=(initializer, *initargs))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k)
            else:
                os.environ[k] = v


def _deaf_to_ctrl_c(initializer, *initargs) -> None:
    """A worker ignores SIGINT: Ctrl-C in a terminal reaches the whole process group, and the sweep's own process
    answers it (one line, the pool terminated); a worker interrupted mid-rollout printed its own traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    initializer(*initargs)
