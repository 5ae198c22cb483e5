"""Peak resident memory and training speed of a named config at a real camera size, for 1 and 4 views.

    python bench/train_memory.py [--config tiny] [--size 96 128] [--views 1 4] [--steps 8] [--impls dense blockwise]

For each (views, attention kernel): a store of 3 random episodes of that many cameras at ``--size`` is written, then
``sc3 train --config CONFIG --data.path STORE --train.steps STEPS`` runs in a fresh process under
``/usr/bin/time -v`` (its maximum resident set size is the peak) with the kernel given as
``--model.attention-impl``; steps/s is the median over the logged steps after the first two (compilation). Prints a
markdown table, then one line per row: ``train_memory <config> views=<v> <impl>: peak_gb=<x> steps_per_s=<y>
tokens=<n>``, and last the ratio of the dense to the blockwise peak at the largest view count."""
from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from sc3_jax.config import load_config, replace
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.model.tokenizer import tokens_per_sample


def store(root: Path, views: int, size: tuple[int, int]) -> Path:
    names = [f"cam{i}" for i in range(views)]
    st = EpisodeStore(root, names, fps=10.0, image_size=size, create=True, action_space=ActionSpace("absolute", 6),
                      state_dim=6, has_pose=False)
    rng = np.random.default_rng(0)
    for e in range(3):
        n = 40
        st.write(Episode(f"ep{e:06d}", {v: rng.integers(0, 256, (n, *size, 3), dtype=np.uint8) for v in names},
                         rng.normal(size=(n, 6)).astype(np.float32), None, state=rng.normal(size=(n, 6)).astype(
                             np.float32)))
    return root


def measure(config: str, data: Path, workdir: Path, steps: int, impl: str) -> tuple[float, float]:
    """(peak resident GB, median steps/s) of one training run in its own process."""
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "sc3_jax.cli", "train", "--config", config, "--data.path",
           str(data), "--train.workdir", str(workdir), "--train.steps", str(steps), "--train.log-every", "1",
           "--train.ckpt-every", str(steps), "--train.no-progress", "--train.no-tensorboard",
           "--model.attention-impl", impl]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        return float("nan"), float("nan")
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr)[1])
    rates = [json.loads(x).get("steps_per_s") for x in (workdir / "metrics.jsonl").read_text().splitlines()]
    rates = [x for x in rates[2:] if x]
    return peak_kb / 2 ** 20, statistics.median(rates) if rates else float("nan")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--config", default="tiny")
    p.add_argument("--size", type=int, nargs=2, default=(96, 128))
    p.add_argument("--views", type=int, nargs="+", default=(1, 4))
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--impls", nargs="+", default=("dense", "blockwise"))
    a = p.parse_args()
    rows, peaks = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for v in a.views:
            data = store(Path(tmp) / f"v{v}", v, tuple(a.size))
            cfg = replace(load_config(a.config), data=dict(views=tuple(f"cam{i}" for i in range(v)),
                                                           image_size=tuple(a.size)), model=dict(num_views=v))
            tokens = tokens_per_sample(cfg)
            for impl in a.impls:
                gb, rate = measure(a.config, data, Path(tmp) / f"run_{v}_{impl}", a.steps, impl)
                peaks[v, impl] = gb
                rows.append((v, impl, tokens, cfg.data.batch_size, gb, rate))
    print("| views | attention | tokens per sample | batch | peak resident GB | steps/s |\n|---|---|---|---|---|---|")
    for v, impl, tokens, batch, gb, rate in rows:
        print(f"| {v} | {impl} | {tokens} | {batch} | {gb:.2f} | {rate:.3f} |")
    for v, impl, tokens, _, gb, rate in rows:
        print(f"train_memory {a.config} views={v} {impl}: peak_gb={gb:.2f} steps_per_s={rate:.3f} tokens={tokens}")
    v = max(a.views)
    if (v, "dense") in peaks and (v, "blockwise") in peaks:
        print(f"train_memory {a.config} views={v}: dense_over_blockwise_peak={peaks[v, 'dense'] / peaks[v, 'blockwise']:.2f}")


if __name__ == "__main__":
    main()
