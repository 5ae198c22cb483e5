"""Peak resident memory and training speed of a named config at a real camera size, for 1 and 4 views.

    python bench/train_memory.py [--config tiny] [--size 96 128] [--views 1 4] [--steps 8] [--impls dense blockwise]
                                 [--max-seconds 300]

For each (views, attention kernel): a store of 3 random episodes of that many cameras at ``--size`` is written, then
``sc3 train --config CONFIG --data STORE --train.steps STEPS`` runs in a fresh process (its peak resident set:
the kernel's VmHWM) with the kernel given as ``--model.attention-impl``, killed after ``--max-seconds`` (the steps
done by then count); steps/s is the median
over the logged steps after the first (compilation). A config that ``sc3 train`` refuses before compiling (it would
not fit this machine: ``memory.fit_to_memory``) reads "refused". Prints a
markdown table, then one line per row: ``train_memory <config> views=<v> <impl>: peak_gb=<x> steps_per_s=<y>
tokens=<n>``, and last the ratio of the dense to the blockwise peak at the largest view count."""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sc3_jax.core.config import load_config, replace
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


def measure(config: str, data: Path, workdir: Path, steps: int, impl: str, seconds: float):
    """(peak resident GB, median steps/s) of one training run in its own process, stopped after ``seconds`` (the
    peak is the kernel's high-water mark of its resident set, VmHWM, read until it ends); None when it was refused."""
    cmd = [sys.executable, "-m", "sc3_jax.cli", "train", "--config", config, "--data", str(data),
           "--train.workdir", str(workdir), "--train.steps", str(steps), "--train.log-every", "1",
           "--train.ckpt-every", str(steps), "--train.no-progress", "--train.no-tensorboard",
           "--model.attention-impl", impl]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak_kb, t0 = 0, time.time()
    while proc.poll() is None and time.time() - t0 < seconds:
        try:
            with open(f"/proc/{proc.pid}/status") as f:
                peak_kb = max(peak_kb, next(int(x.split()[1]) for x in f if x.startswith("VmHWM:")))
        except (OSError, StopIteration):
            pass
        time.sleep(0.5)
    if proc.poll() is None:
        proc.kill()
    _, err = proc.communicate()
    log = workdir / "metrics.jsonl"
    if "error:" in err and not log.exists():
        return None
    rates = [json.loads(x).get("steps_per_s") for x in log.read_text().splitlines()] if log.exists() else []
    rates = [x for x in rates[1:] if x]
    return peak_kb / 2 ** 20, statistics.median(rates) if rates else float("nan")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--config", default="tiny")
    p.add_argument("--size", type=int, nargs=2, default=(96, 128))
    p.add_argument("--views", type=int, nargs="+", default=(1, 4))
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--impls", nargs="+", default=("dense", "blockwise"))
    p.add_argument("--max-seconds", type=float, default=300.0)
    a = p.parse_args()
    rows, peaks = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for v in a.views:
            data = store(Path(tmp) / f"v{v}", v, tuple(a.size))
            cfg = replace(load_config(a.config), data=dict(views=tuple(f"cam{i}" for i in range(v)),
                                                           image_size=tuple(a.size)), model=dict(num_views=v))
            tokens = tokens_per_sample(cfg)
            for impl in a.impls:
                got = measure(a.config, data, Path(tmp) / f"run_{v}_{impl}", a.steps, impl, a.max_seconds)
                gb, rate = got if got else (float("nan"), float("nan"))
                peaks[v, impl] = gb
                rows.append((v, impl, tokens, cfg.data.batch_size, gb, rate, got is None))
    print("| views | attention | tokens per sample | batch | peak resident GB | steps/s |\n|---|---|---|---|---|---|")
    for v, impl, tokens, batch, gb, rate, refused in rows:
        print(f"| {v} | {impl} | {tokens} | {batch} | " + ("refused before compiling | - |" if refused else
                                                             f"{gb:.2f} | {rate:.4f} |"))
    for v, impl, tokens, _, gb, rate, refused in rows:
        print(f"train_memory {a.config} views={v} {impl}: " + ("refused" if refused else
                                                              f"peak_gb={gb:.2f} steps_per_s={rate:.4f}")
              + f" tokens={tokens}")
    v = min(a.views)
    if (v, "dense") in peaks and (v, "blockwise") in peaks:
        print(f"train_memory {a.config} views={v}: dense_over_blockwise_peak="
              f"{peaks[v, 'dense'] / peaks[v, 'blockwise']:.2f}")


if __name__ == "__main__":
    main()
