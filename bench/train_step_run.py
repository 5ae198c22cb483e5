"""Where a real run's training step goes, against the chip's own matmul ceiling, measured in one run.

    python bench/train_step.py --run RUN [--steps 20] [--rounds 2]      # RUN: a `sc3 train` workdir (the SO-101 trunk)

RUN's config exactly as it trains (its model, batch, tokenizer and data store; its cached latents shared, read only),
on this process's devices. Per round, interleaved so every figure sees the same machine load:

* ceiling: a square float32 matmul's GFLOP/s on the same devices;
* step alone: the compiled step on a batch already on the device (GFLOP/s from XLA's cost analysis of the step with
  its layer scan unrolled: the scan's body is otherwise counted once);
* data: one batch read from the store (the grain iterator) and put on the device -- on the critical path when the
  loop reads it between steps;
* loop: the training loop's own sequence (read, put, step) timed over ``--steps`` steps with the metrics fetched every
  ``train.log_every`` (the loop's host syncs), and again with them fetched every step (what a sync costs);
* recompiles: the step's compile-cache entries after the loop (1: none);
* attention: the step alone with each ``--impls`` kernel (``model.attention_impl``, which a resumed run may change),
  and with attention replaced by a pass-through (its share of the step: the time it saves).

Last lines: `train_step_run <run>: gflops_per_s=... ceiling_gflops_per_s=... fraction_of_matmul=... step_s=...
data_s=... loop_s=...` and the shares of the loop's time."""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

from sc3_jax.core import atomic  # noqa: E402
from sc3_jax.core.config import config_from_dict, replace  # noqa: E402
from sc3_jax.core.xla_cost import flops  # noqa: E402
from sc3_jax.model import sharding  # noqa: E402
from sc3_jax.train import train  # noqa: E402
from train_step import matmul_flops_per_s  # noqa: E402


def run_config(run: Path, scratch: Path):
    """RUN's config writing nowhere of RUN's: a scratch workdir sharing RUN's latents and norm stats."""
    cfg = config_from_dict(atomic.read_json(run / "config.json"))
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, workdir=str(scratch), progress=False,
                                                             init_from=None, resume_from=None))
    scratch.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run / "norm_stats.json", scratch / "norm_stats.json")
    if (run / "latents").is_dir():
        os.symlink((run / "latents").absolute(), scratch / "latents")
    return cfg


class RunBench:
    def __init__(self, run: Path, scratch: Path, impl: str | None = None, count_flops: bool = True):
        self.cfg = cfg = run_config(run, scratch)
        if impl is not None:
            self.cfg = cfg = replace(cfg, model=dict(attention_impl=impl))
        self.mesh = sharding.make_mesh(cfg.mesh)
        _, _, self.data = train.prepare_data(cfg)
        self.step, _ = train.compile_train_step(cfg, self.mesh)
        self.state = train.create_state(cfg, self.mesh)
        self.batch = self.next_batch()
        if count_flops:
            unrolled = replace(cfg, model=dict(scan_layers=False))
            counted, _ = train.compile_train_step(unrolled, self.mesh)
            self.flops = flops(counted.lower(self.state, self.batch), compiled=True)
        jax.block_until_ready(self.run_step(self.batch))  # compiled once here: every timing below is warm

    def next_batch(self):
        return sharding.global_batch(self.mesh, train._model_batch(next(self.data), self.cfg))

    def run_step(self, batch):
        self.state, metrics = self.step(self.state, batch)  # the state is donated: keep the new one
        return metrics

    def step_alone(self, repeats: int) -> float:
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(self.run_step(self.batch))
            best = min(best, time.perf_counter() - t0)
        return best

    def data_alone(self, repeats: int) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(self.next_batch())
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    def loop(self, steps: int, fetch_every: int) -> float:
        """Seconds per step of the loop's sequence, the metrics fetched to the host every ``fetch_every`` steps."""
        t0 = time.perf_counter()
        pending = []
        for i in range(steps):
            pending.append(self.run_step(self.next_batch()))
            if len(pending) >= fetch_every or i == steps - 1:
                jax.device_get(pending)
                pending = []
        return (time.perf_counter() - t0) / steps

    def compiles(self) -> int:
        fn = getattr(self.step, "fn", self.step)
        return fn._cache_size() if hasattr(fn, "_cache_size") else -1


def step_variant(run: Path, scratch: Path, impl: str | None, repeats: int, passthrough: bool = False) -> float:
    """The step alone with attention kernel ``impl``, or (``passthrough``) with every attention call returning its
    queries (no scores, no softmax, no weighted sum): what attention costs is the difference."""
    from sc3_jax.model import attention_impl

    real = attention_impl.attend
    if passthrough:
        attention_impl.attend = lambda impl, q, k, v, mask=None, block=512: q
    try:
        return RunBench(run, scratch, impl, count_flops=False).step_alone(repeats)
    finally:
        attention_impl.attend = real


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--impls", nargs="*", default=["dense", "fused"], help="attention kernels to time the step with")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        b = RunBench(a.run, Path(tmp) / "work")
        log_every = b.cfg.train.log_every
        rows = []
        for r in range(a.rounds):
            row = {"ceiling": matmul_flops_per_s(repeats=a.repeats), "step": b.step_alone(a.repeats),
                   "data": b.data_alone(a.repeats), "loop": b.loop(a.steps, log_every), "loop_sync": b.loop(a.steps, 1)}
            rows.append(row)
            print(f"round {r}: matmul {row['ceiling'] / 1e9:.1f} GFLOP/s; step alone {row['step']:.3f} s "
                  f"({b.flops / row['step'] / 1e9:.1f} GFLOP/s); one batch read + put {row['data']:.3f} s; loop "
                  f"{row['loop']:.3f} s/step (fetch every {log_every}), {row['loop_sync']:.3f} (every step)", flush=True)
        variants = {f"attention {impl}": step_variant(a.run, Path(tmp) / f"w_{impl}", impl, a.repeats)
                    for impl in a.impls}
        variants["attention pass-through"] = step_variant(a.run, Path(tmp) / "w_none", None, a.repeats, True)
        variants["as run"] = b.step_alone(a.repeats)  # the run's own kernel again, after the variants
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(f"train_step_run {a.run.name}: {b.flops / 1e9:.1f} GFLOP/step, batch {b.cfg.data.batch_size}, "
          f"{jax.device_count()} {jax.devices()[0].platform} device(s); compiles after the loop: {b.compiles()}")
    print(f"train_step_run {a.run.name}: gflops_per_s={b.flops / med['step'] / 1e9:.1f} "
          f"ceiling_gflops_per_s={med['ceiling'] / 1e9:.1f} fraction_of_matmul={b.flops / med['step'] / med['ceiling']:.3f} "
          f"step_s={med['step']:.3f} data_s={med['data']:.3f} loop_s={med['loop']:.3f} loop_sync_s={med['loop_sync']:.3f}")
    loop = med["loop"]
    print(f"train_step_run {a.run.name}: of the loop's {loop:.3f} s/step: compute {med['step'] / loop:.0%}, "
          f"the rest {(loop - med['step']) / loop:.0%} (data on the critical path ~{med['data'] / loop:.0%}); a "
          f"metrics sync every step would add {(med['loop_sync'] - loop) / loop:+.0%}")
    base = variants["as run"]
    print(f"train_step_run {a.run.name}: step alone by attention kernel (the run's: {b.cfg.model.attention_impl}): "
          + "; ".join(f"{k} {v:.3f} s ({v / base:.2f}x)" for k, v in variants.items()))
    print(f"train_step_run {a.run.name}: attention's share of the step ~"
          f"{max(0.0, base - variants['attention pass-through']) / base:.0%}")


if __name__ == "__main__":
    main()
