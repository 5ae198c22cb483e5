"""A lab's first world model, timed: a two-camera 240x320 LeRobot dataset (synthetic frames, 4-D delta actions, a
14-D state, 10 fps, like a recorded SO-101 one) imported at 96x128, then `sc3 train` on it two ways, in one run:
the default path (`tiny`, its patch and batch sized from the data: sizing.py) and `tiny` before sizing (8-pixel
patches and batch 32 whatever the image: `--model.patch-size 8 --batch 32`).

    python bench/first_run.py [--steps 30] [--old-steps 4] [--workdir DIR]

Per run: tokens a frame and a sample, the estimate `sc3 train` printed before compiling, steps/s after
compilation (the last logged window, from metrics.jsonl) and the peak resident memory of the training process.
Last lines: `first_run <name>: steps_per_s=<x> peak_gb=<y> sample_tokens=<n>` and the ratio of the two rates."""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from sc3_jax.benchmarks.so101.collect import action_space
from sc3_jax.data.lerobot import INFO_ACTION_SPACE
from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot
from sc3_jax.data.synthetic import rollout

VIEWS = ("front", "wrist")


def make_dataset(out: Path, episodes: int = 18, length: int = 60, size=(240, 320)) -> None:
    """Synthetic frames (two of the synthetic env's views, rendered small and scaled up, as a camera's smooth
    frames), 4-D actions and a 14-D state random walk."""
    def raws():
        for i in range(episodes):
            ep = rollout((60, 80), length, np.random.SeedSequence([7, i]))
            frames = {f"observation.images.{v}": np.stack([cv2.resize(f, size[::-1]) for f in ep.frames[src]])
                      for v, src in zip(VIEWS, ("left", "wrist"))}
            act = np.concatenate([np.clip(ep.actions[:, :3] * 20, -1, 1), (ep.actions[:, 6:7] > 0)], 1)
            state = np.cumsum(np.random.default_rng(i).normal(0, 0.05, (length, 14)), 0)
            yield RawEpisode(frames, act.astype(np.float32), "move the blocks", state.astype(np.float32))
    write_lerobot(out, raws(), fps=10, robot_type="so101", info={INFO_ACTION_SPACE: action_space()})


def train(store: Path, workdir: Path, steps: int, extra: list[str]) -> dict:
    """`sc3 train` in a child process, from nothing (a run of an earlier bench is removed): its printed cost line,
    steps/s of the last logged window, peak RSS."""
    shutil.rmtree(workdir, ignore_errors=True)
    cmd = [sys.executable, "-m", "sc3_jax.cli", "train", "--data", str(store), "--train.workdir", str(workdir),
           "--train.steps", str(steps), "--train.log-every", str(max(1, steps // 3)), "--train.no-progress", *extra]
    t0 = time.time()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = p.stdout.read()
    _, status, usage = os.wait4(p.pid, 0)
    if status:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out}")
    rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    rate = [r["steps_per_s"] for r in rows if "steps_per_s" in r][-1]
    cost = next((line for line in out.splitlines() if line.startswith("cost:")), "")
    tokens = re.search(r"(\d+) a sample", cost)
    return {"steps_per_s": rate, "peak_gb": usage.ru_maxrss * 1024 / 1e9, "wall_s": time.time() - t0,
            "sample_tokens": int(tokens.group(1)) if tokens else None, "cost_line": cost}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=30, help="steps of the default run")
    ap.add_argument("--old-steps", type=int, default=4, help="steps of today's tiny (~50 s each on 2 cores; 0: skip)")
    ap.add_argument("--workdir", default=None, help="keep the dataset and runs here (default: a temporary folder)")
    a = ap.parse_args()
    root = Path(a.workdir or tempfile.mkdtemp(prefix="sc3-first-run-"))
    lerobot, store = root / "lerobot", root / "store"
    if not store.exists():
        t0 = time.time()
        make_dataset(lerobot)
        subprocess.run([sys.executable, "-m", "sc3_jax.cli", "data", "import-lerobot", "--data", str(lerobot), "--out",
                        str(store), "--image-size", "96", "128"], check=True, stdout=subprocess.DEVNULL)
        print(f"dataset: 18 episodes, two 240x320 cameras, imported at 96x128 ({time.time() - t0:.0f} s)")
    runs = {"default": train(store, root / "default", a.steps, [])}
    if a.old_steps:
        runs["tiny_before"] = train(store, root / "tiny_before", a.old_steps,
                                    ["--model.patch-size", "8", "--batch", "32"])
    for name, r in runs.items():
        print(f"  {name}: {r['cost_line']}")
    for name, r in runs.items():
        print(f"first_run {name}: steps_per_s={r['steps_per_s']:.3f} peak_gb={r['peak_gb']:.2f} "
              f"sample_tokens={r['sample_tokens']} wall_s={r['wall_s']:.0f}")
    if "tiny_before" in runs:
        print(f"first_run ratio: default/tiny_before steps_per_s="
              f"{runs['default']['steps_per_s'] / runs['tiny_before']['steps_per_s']:.1f}x")


if __name__ == "__main__":
    main()
