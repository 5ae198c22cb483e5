"""Train-step throughput as a fraction of what this machine's plain jitted matmul reaches, measured side by side.

    python bench/train_step.py [--configs tiny cpu_medium] [--rounds 3]
    python bench/train_step.py --run RUN [--steps 20]    # a real run (the SO-101 trunk): bench/train_step_run.py

FLOPs per step come from XLA's cost analysis of the compiled step with the layer scan unrolled (the cost analysis
counts a loop body once, which would undercount a depth-L model by ~L x); the timed step is the config as it trains
(scanned layers). The matmul reference is a square fp32 matmul of a size that saturates the CPU. Rounds alternate matmul and train-step timings so both see the same machine load.
Last lines: `train_step <config>: fraction_of_matmul=<x> tokens_per_s=<y>`."""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.model import sharding
from sc3_jax.train import train
from sc3_jax.core.config import MeshConfig, load_config, replace
from sc3_jax.model.tokenizer import tokens_per_sample


def timed(fn, *args, repeats: int) -> float:
    """Best wall time of ``repeats`` calls (after one warm-up), blocking on the result."""
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def matmul_flops_per_s(n: int = 1024, repeats: int = 5) -> float:
    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32)
    f = jax.jit(lambda a, b: a @ b)
    return 2 * n ** 3 / timed(f, a, b, repeats=repeats)


class StepBench:
    def __init__(self, name: str):
        cfg = load_config(name)
        self.cfg = replace(cfg, mesh=MeshConfig(1, 1, 1))
        mesh = sharding.make_mesh(self.cfg.mesh, jax.devices()[:1])
        step, _ = train.compile_train_step(self.cfg, mesh)
        self.state = train.create_state(self.cfg, mesh)
        rng = np.random.default_rng(0)
        shapes = train.batch_shapes(self.cfg)
        self.batch = sharding.global_batch(mesh, {
            "frames": rng.integers(0, 256, shapes["frames"].shape, dtype=np.uint8),
            "actions": rng.normal(size=shapes["actions"].shape).astype(np.float32),
            "stride": np.ones(shapes["stride"].shape, np.int32)})
        self.step = step.lower(self.state, self.batch).compile()
        unrolled = replace(self.cfg, model=dict(scan_layers=False))
        counted, _ = train.compile_train_step(unrolled, mesh)
        cost = counted.lower(self.state, self.batch).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        self.flops = float(cost["flops"])
        self.tokens = self.cfg.data.batch_size * tokens_per_sample(self.cfg)

    def seconds(self, repeats: int) -> float:
        def run():
            self.state, metrics = self.step(self.state, self.batch)  # state is donated: keep the new one
            return metrics["loss"]
        run()
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(run())
            best = min(best, time.perf_counter() - t0)
        return best


def main():
    if "--run" in sys.argv:  # a real run's step, data and loop: its own bench
        import train_step_run
        sys.argv.remove("--run")
        return train_step_run.main()
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--configs", nargs="+", default=["tiny", "cpu_medium"])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    benches = {name: StepBench(name) for name in args.configs}
    fractions = {name: [] for name in benches}
    rates = {name: [] for name in benches}
    for r in range(args.rounds):
        for name, b in benches.items():
            ref = matmul_flops_per_s(repeats=args.repeats)
            sec = b.seconds(args.repeats)
            fractions[name].append(b.flops / sec / ref)
            rates[name].append(b.tokens / sec)
            print(f"round {r} {name}: step {sec * 1e3:.1f} ms, {b.flops / sec / 1e9:.1f} GFLOP/s "
                  f"(matmul {ref / 1e9:.1f} GFLOP/s), {b.flops / 1e9:.2f} GFLOP/step, {b.tokens} tokens/step",
                  flush=True)
    for name in benches:
        print(f"train_step {name}: fraction_of_matmul={statistics.median(fractions[name]):.3f} "
              f"tokens_per_s={statistics.median(rates[name]):.0f}")


if __name__ == "__main__":
    main()
