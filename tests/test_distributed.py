"""Two processes on localhost with jax.distributed get the same loss as one process with 8 devices."""
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from test_sharding import one_step, small_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # 71 s: the default run stays under 15 min on 2 cores; CI runs it
def test_two_processes_match_one():
    port = free_port()
    worker = Path(__file__).with_name("_dist_worker.py")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    procs = [subprocess.Popen(["timeout", "240", sys.executable, str(worker), str(i), str(port)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=260) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, f"worker failed:\n{out}\n{err[-3000:]}"
    losses = [float(next(l for l in out.splitlines() if l.startswith("LOSS")).split()[1]) for out, _ in outs]
    assert losses[0] == losses[1]
    ref_loss, _, _ = one_step(small_config((8, 1, 1)), jax.devices())
    assert losses[0] == pytest.approx(ref_loss, rel=1e-5)
