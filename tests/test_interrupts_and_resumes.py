"""Ctrl-C ends a command with exit 130 and one line at any phase (here: `sc3 train` while it compiles, which segfaulted
in the interpreter's teardown), and a resumed training run logs each step once in metrics.jsonl (a run stopped
after logging steps its last checkpoint did not reach logged them again on resume)."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sc3_jax.train import train
from sc3_jax.core.config import load_config, replace
from sc3_jax.data import synthetic

SMALL = dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, mlp_dim=64)  # a cheap tiny model: widths only


@pytest.fixture
def ctrl_c_reaches_children():
    """SIGINT at its default in the commands started here, as in a terminal (a shell running pytest in the
    background without job control hands it on ignored; see test_untrusted_inputs.py)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    root = tmp_path_factory.mktemp("episodes") / "store"
    synthetic.generate(root, 4, length=24, seed=0)
    return root


def test_ctrl_c_while_sc3_train_compiles_exits_130_in_one_line(episodes, tmp_path, ctrl_c_reaches_children):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "sc3_jax.cli", "train", "--config", "tiny", "--data", str(episodes), "--batch", "8",
           "--train.workdir", str(run), "--train.steps", "50", "--train.no-progress",
           "--train.no-tensorboard", *[a for k, v in SMALL.items() for a in (f"--model.{k}", str(v))]]
    proc = subprocess.Popen(cmd, env={**os.environ, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    seen = []
    for line in proc.stdout:  # the sizing it prints just before train.train: then it reads the data and compiles
        seen.append(line)
        if "to cut it:" in line:
            break
    assert proc.poll() is None, (seen, proc.stderr.read()[-3000:])
    time.sleep(2.0)  # into the compile of the train step (tens of seconds on 2 shared cores)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert lines[-1] == ("sc3 train: interrupted; nothing half-written is left; the same command resumes from its "
                         "last checkpoint") and "Traceback" not in err, err[-3000:]
    assert not (run / "metrics.jsonl").exists()  # stopped before its first step: while it prepared or compiled


@pytest.mark.slow
def test_ctrl_c_while_a_sweeps_workers_run_exits_130_in_one_line(tmp_path, ctrl_c_reaches_children):
    """`sc3 sweep bench --workers 2`: spawned workers roll out in the simulator when Ctrl-C reaches the whole
    process group; the command's line is the last (no worker traceback, no resource tracker's warning after it),
    and the store resumes."""
    import jax

    from sc3_jax.benchmarks.bussing import perception
    from test_sweep import tiny_world_model

    wm = tiny_world_model(tmp_path)
    perception.save(tmp_path / "perception.npz", perception.init(jax.random.key(1)))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "sc3_jax.cli", "sweep", "bench", "--world-model", str(wm), "--perception",
           str(tmp_path / "perception.npz"), "--episodes", "2", "--calibration-episodes", "1", "--ceiling-episodes",
           "1", "--episode-seconds", "1.6", "--batch", "2", "--workers", "2", "--no-progress", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    results, t0 = out / "results.jsonl", time.time()
    while proc.poll() is None and time.time() - t0 < 300 and not (results.exists() and results.read_text()):
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[1][-3000:]
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: every process of the group
    _, err = proc.communicate(timeout=120)
    time.sleep(1.0)  # a resource tracker outliving the command would write its warning by now
    assert proc.returncode == 130, err[-3000:]
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert lines[-1] == ("sc3 sweep: interrupted; nothing half-written is left; the same command resumes it "
                         "(finished rollouts are kept)") and "Traceback" not in err, err[-3000:]
    from sc3_jax.evaluation.results import ResultsStore
    assert ResultsStore(out).records()  # whole records kept, readable


def test_a_resumed_runs_log_drops_the_rows_its_checkpoint_did_not_reach(tmp_path):
    log = tmp_path / "metrics.jsonl"
    log.write_text("".join(json.dumps({"step": s, "loss": 1.0 / s}) + "\n" for s in range(1, 8)) + "not json\n")
    train.MetricsLog(tmp_path, tensorboard=False, resumed_at=4).write([{"step": 5, "loss": 0.5}])
    rows = [json.loads(x) for x in log.read_text().splitlines() if x.startswith("{")]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5] and rows[-1]["loss"] == 0.5
    assert "not json" in log.read_text()  # a line that is no row is kept (read_metrics names it)
    train.MetricsLog(tmp_path, tensorboard=False).write([{"step": 6}])  # no resume step given: nothing dropped
    assert [json.loads(x)["step"] for x in log.read_text().splitlines() if x.startswith("{")] == [1, 2, 3, 4, 5, 6]


@pytest.mark.slow
def test_a_resumed_training_run_logs_each_step_once(episodes, tmp_path):
    cfg = replace(load_config("tiny"), model=SMALL, data=dict(path=str(episodes), batch_size=8),
                  train=dict(workdir=str(tmp_path / "run"), steps=4, log_every=1, ckpt_every=2, progress=False,
                             tensorboard=False, async_checkpointing=False))
    train.train(cfg)
    run = Path(cfg.train.workdir)
    assert {2, 4} <= {int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit()}
    shutil.rmtree(run / "checkpoints" / "4")  # stopped after logging steps 3-4, before their checkpoint was kept
    train.train(replace(cfg, train=dict(steps=6)))  # resumes at step 2: steps 3-6 run (3-4 again)
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5, 6]
    # the run's files say what it did: the rate each update used (on the resumed length's schedule from step 3) and
    # the length it now has (a lengthened run's config.json once kept its first length)
    six = train.lr_schedule(replace(cfg, train=dict(steps=6)).train)
    assert [r["lr"] for r in rows[2:]] == pytest.approx([float(six(s - 1)) for s in (3, 4, 5, 6)])
    assert json.loads((run / "config.json").read_text())["train"]["steps"] == 6


def test_serving_a_policy_lets_ctrl_c_through_after_shutting_down():
    """sc3 serve-policy exits 130 on Ctrl-C like every command: the server shuts down, the interrupt is not eaten."""
    from sc3_jax.policies.openpi_server import serve_until_interrupted

    class Server:
        down = False

        def serve_forever(self):
            raise KeyboardInterrupt

        def shutdown(self):
            self.down = True

    s = Server()
    with pytest.raises(KeyboardInterrupt):
        serve_until_interrupted(s)
    assert s.down


def test_a_resumed_tokenizer_logs_each_step_once(tmp_path):
    """The tokenizer's metrics.jsonl, like the world model's, drops the rows past the checkpoint it resumes from."""
    from sc3_jax.core import atomic

    log = tmp_path / "metrics.jsonl"
    log.write_text("".join(json.dumps({"step": i}) + "\n" for i in range(1, 8)) + "not json\n")
    assert atomic.drop_rows_after(log, 4) == 3
    assert log.read_text().splitlines() == [json.dumps({"step": i}) for i in range(1, 5)] + ["not json"]
    assert atomic.drop_rows_after(log, 4) == 0 and atomic.drop_rows_after(tmp_path / "none.jsonl", 1) == 0
