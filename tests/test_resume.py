"""A training run killed with SIGKILL after a checkpoint and restarted continues with exactly the losses (and so
the data order and random draws) of an uninterrupted run."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sc3_jax.data import synthetic
from sc3_jax.train.train import read_metrics

STEPS = 150

CONFIG = '''
from sc3_jax.core.config import Config, DataConfig, ModelConfig, TrainConfig
def get_config(arg=None):
    return Config(model=ModelConfig(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                    rope_axes_dim=(2, 3, 3)),
                  data=DataConfig(path={data!r}, image_size=(8, 8), context_frames=1, future_frames=2,
                                  batch_size=4),
                  train=TrainConfig(workdir={workdir!r}, steps={steps}, ckpt_every=5, log_every=1, lr=1e-3,
                                    warmup_steps=2, progress=False, tensorboard=False))
'''


def _start(tmp: Path, name: str, data: str) -> tuple[subprocess.Popen, Path]:
    workdir = tmp / name
    cfg = tmp / f"{name}.py"
    cfg.write_text(CONFIG.format(data=data, workdir=str(workdir), steps=STEPS))
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    proc = subprocess.Popen([sys.executable, "-m", "sc3_jax.cli", "train", "--config", str(cfg)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, workdir


def _finished_checkpoints(workdir: Path) -> list[int]:
    d = workdir / "checkpoints"
    return sorted(int(p.name) for p in d.iterdir() if p.name.isdigit()) if d.exists() else []


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_sigkill_then_resume_matches_uninterrupted(tmp_path):
    data = str(tmp_path / "episodes")
    synthetic.generate(data, 6, length=30, image_size=(8, 8), seed=0, progress=False)

    ref, ref_dir = _start(tmp_path, "ref", data)
    killed, run_dir = _start(tmp_path, "run", data)
    deadline = time.time() + 300
    while not _finished_checkpoints(run_dir) or max(_finished_checkpoints(run_dir)) < 10:
        assert killed.poll() is None, killed.stdout.read()
        assert time.time() < deadline, "no checkpoint appeared"
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    before = read_metrics(run_dir)
    assert max(before) < STEPS, "the run finished before it could be killed: the test proves nothing"

    resumed, _ = _start(tmp_path, "run", data)
    out, _ = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, out
    assert ref.wait(timeout=300) == 0, ref.stdout.read()
    a, b = read_metrics(ref_dir), read_metrics(run_dir)
    assert sorted(a) == sorted(b) == list(range(1, STEPS + 1))
    for step in a:
        assert b[step]["loss"] == pytest.approx(a[step]["loss"], rel=1e-6, abs=1e-9), step
