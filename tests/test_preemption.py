"""SIGTERM, what a scheduler sends before it preempts a job: `sc3 train` saves a checkpoint at the next step, says
where it stopped and exits 143 -- not "done", and without going on to the learned state -- and the same command
resumes it to the end."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from sc3_jax.data import synthetic

pytestmark = pytest.mark.slow  # two tiny trainings in subprocesses (compiles): ~1 min on 2 cores


def test_sigterm_saves_stops_with_143_and_the_same_command_resumes_to_the_end(tmp_path):
    synthetic.generate(tmp_path / "data", 4, length=24)
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "sc3_jax.cli", "train", "--config", "tiny", "--data", str(tmp_path / "data"),
           "--train.workdir", str(run), "--train.steps", "400", "--train.log-every", "1", "--train.ckpt-every",
           "1000", "--train.no-progress", "--train.no-tensorboard"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    metrics = run / "metrics.jsonl"
    deadline = time.time() + 300
    while not (metrics.exists() and metrics.read_text().count("\n") >= 2):  # it is training
        assert p.poll() is None and time.time() < deadline, p.communicate()
        time.sleep(0.5)
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=300)
    assert p.returncode == 143, (out, err)
    assert "stopped at step" in out and "rerun the same command" in out and "done:" not in out, out
    stopped = json.loads(metrics.read_text().splitlines()[-1])["step"]
    assert 2 <= stopped < 400 and (run / "checkpoints" / str(stopped)).is_dir()
    # resumed with a shorter run: it ends there, exactly once per step in metrics.jsonl
    end = stopped + 2
    again = subprocess.run(cmd[:cmd.index("400")] + [str(end)] + cmd[cmd.index("400") + 1:], capture_output=True,
                           text=True, cwd=tmp_path, timeout=300, env=os.environ)
    assert again.returncode == 0 and f"done: step {end}" in again.stdout, (again.stdout, again.stderr)
    steps = [json.loads(line)["step"] for line in metrics.read_text().splitlines()]
    assert steps == list(range(1, end + 1))
    # and once more: nothing left to train, said so (it printed "done: step None loss nan")
    done = subprocess.run(cmd[:cmd.index("400")] + [str(end)] + cmd[cmd.index("400") + 1:], capture_output=True,
                          text=True, cwd=tmp_path, timeout=300, env=os.environ)
    assert done.returncode == 0 and "nothing to train" in done.stdout and "None" not in done.stdout, done.stdout
