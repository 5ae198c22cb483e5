"""launch/gpu_playbook.py: its dry run takes every phase (mixture, fine-tune of the shipped model, sweep, 1-step
student, bench) through
on the CPU and leaves what a device call may bring back; its sweep runs the archived store's protocol; its
exports fit a call's return and its deadlines stop whole process groups."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NAME = re.compile(r"^[A-Za-z0-9._-]+$")


sys.path.insert(0, str(ROOT / "launch"))
import gpu_playbook as pb  # noqa: E402


def test_the_sweep_runs_the_archived_stores_protocol_on_both_splits():
    from sc3_jax.commands import parse
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig

    ctx = pb.Ctx(pb.Args("sweep"), Path("/r"), Path("/o"), 0.0)
    cfg = parse(SweepConfig, pb._sweep_protocol(ctx), "sweep")
    archived = json.loads((pb.ARCHIVE / "sweep.json").read_text())
    mine = cfg.to_json()
    for k in pb.PROTOCOL:
        assert mine[k] == archived[k], k
    assert archived["episodes"] == 72 and tuple(cfg.tasks) == ("bussing", "reverse")
    assert cfg.degradations == "all" and archived["degradations"] is True


def test_training_reaches_three_times_the_shipped_windows_from_the_shipped_model(tmp_path):
    ctx = pb.Ctx(pb.Args("train", run=str(tmp_path)), tmp_path, tmp_path, 0.0)
    steps, batch = pb._train_target(ctx)
    assert steps * batch >= 3 * 128_000 and batch == 64
    cmd = pb._trainer_cmd(ctx, steps)
    assert cmd[cmd.index("--train.init-from") + 1] == str(pb.SHIPPED) and (pb.SHIPPED / "params.npz").exists()
    assert cmd[cmd.index("--config") + 1] == "bussing_latent_gpu"
    flags = [c for c in cmd if c.startswith("--")]
    assert len(flags) == len(set(flags)), "an option given twice"


def test_the_student_is_distilled_from_the_shipped_model_in_its_own_workdir(tmp_path):
    ctx = pb.Ctx(pb.Args("distill", run=str(tmp_path), distill_steps=700, distill_lr=5e-5), tmp_path, tmp_path, 0.0)
    steps, batch = pb._train_target(ctx, "distill")
    assert (steps, batch) == (700, 64)
    cmd = pb._trainer_cmd(ctx, steps, "distill")
    opt = {k: cmd[cmd.index(k) + 1] for k in ("--flow.distill-teacher", "--train.init-from", "--train.workdir",
                                                "--train.lr", "--train.steps")}
    assert opt == {"--flow.distill-teacher": str(pb.SHIPPED), "--train.init-from": str(pb.SHIPPED),
                   "--train.workdir": str(tmp_path / "distill"), "--train.lr": "5e-05", "--train.steps": "700"}
    flags = [c for c in cmd if c.startswith("--")]
    assert len(flags) == len(set(flags)), "an option given twice"
    assert "--flow.distill-teacher" not in pb._trainer_cmd(ctx, steps)  # the fine-tune has no teacher


def test_exports_fit_a_calls_return_and_deadlines_stop_process_groups(tmp_path):
    ctx = pb.Ctx(pb.Args("data"), tmp_path, tmp_path / "out", 0.0)
    ctx.out.mkdir()
    big = tmp_path / "big"
    big.mkdir()
    (big / "x.bin").write_bytes(os.urandom(20 * 2**20))  # incompressible: two parts
    names = pb.ship(ctx, "model_1.tgz", [(big, "big")])
    assert names == ["model_1.tgz.00", "model_1.tgz.01"]
    assert all((ctx.out / n).stat().st_size <= 16 * 2**20 for n in names)
    joined = tmp_path / "joined.tgz"
    joined.write_bytes(b"".join((ctx.out / n).read_bytes() for n in names))
    with tarfile.open(joined) as tar:
        assert tar.extractfile("big/x.bin").read() == (big / "x.bin").read_bytes()
    # a child of the child outlives nothing: the deadline ends the whole group
    t0 = time.time()
    rc = pb.call([sys.executable, "-c", "import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', "
                  "'import time; time.sleep(60)']); time.sleep(60)"], tmp_path / "log", seconds=2)
    assert rc != 0 and time.time() - t0 < 30 and "stopped at its deadline" in (tmp_path / "log").read_text()


def test_preflight_counts_what_a_call_sends_and_the_wheels_it_lacks(tmp_path, capsys):
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / ".gitignore").write_text("runs/\n.whl/\n")
    (tmp_path / "a.py").write_bytes(b"x" * 1000)
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "big.bin").write_bytes(b"x" * 10**6)  # ignored: does not travel
    (tmp_path / ".whl").mkdir()
    (tmp_path / ".whl" / "tyro-1.0.17-py3-none-any.whl").write_bytes(b"x" * 500)  # ignored but carried
    assert pb.travel_bytes(tmp_path) == 1000 + 500 + len("runs/\n.whl/\n")
    missing = pb.missing_wheels(tmp_path)
    assert "tyro" not in missing and "mujoco" in missing and "grain" in missing
    assert pb.preflight(tmp_path) == 1  # wheels and GL loaders missing
    out = capsys.readouterr().out
    assert "missing docstring_parser" in out and "0 .deb files" in out


@pytest.mark.slow
def test_the_dry_run_takes_every_phase_through_on_the_cpu(tmp_path):
    run, out = tmp_path / "run", tmp_path / "out"
    env = dict(os.environ)
    # one CPU device, as on a user's machine (the test session forces 8 for the sharding tests)
    env["XLA_FLAGS"] = re.sub(r"--xla_force_host_platform_device_count=\d+", "", env.get("XLA_FLAGS", ""))
    cmd = [sys.executable, str(ROOT / "launch" / "gpu_playbook.py"), "--phase", "all", "--dry-run", "--run",
           str(run), "--out", str(out)]
    p = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1500)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    for phase in pb.PHASES:
        assert f"== phase {phase}" in p.stdout
    assert re.search(r"device minutes per phase so far: data [\d.]+, train [\d.]+, sweep [\d.]+, distill [\d.]+, "
                     r"bench [\d.]+; ", p.stdout)
    files = sorted(f.name for f in out.iterdir())
    assert all(NAME.match(f) and (out / f).stat().st_size <= 16 * 2**20 for f in files)
    for phase in pb.PHASES:  # each phase's exports fit one call's 8 files
        res = json.loads((out / f"{phase}.json").read_text())
        assert len(res["exports"]) + 1 <= 8 and all((out / f).exists() for f in res["exports"])
    # data: the mixture and its outcome mix beside the zoo's real one
    assert json.loads((out / "data.json").read_text())["episodes"] == 3
    assert "in distribution (bussing)" in (out / "data_stats.txt").read_text()
    # train: the shipped model fine-tuned two steps, brought back as an int8 export with the state reader
    train = json.loads((out / "train.json").read_text())
    assert train["step"] == 2 and train["windows"] == 4 and not train["trainer_running"]
    parts = sorted(f for f in files if f.startswith("model_2.tgz"))
    (tmp_path / "m.tgz").write_bytes(b"".join((out / f).read_bytes() for f in parts))
    with tarfile.open(tmp_path / "m.tgz") as tar:
        tar.extractall(tmp_path / "model")
    m = tmp_path / "model" / "export_2"
    assert {"config.json", "params.npz", "norm_stats.json", "state_reader.npz", "tokenizer", "data_stats.json"} <= {
        f.name for f in m.iterdir()}
    assert json.loads((m / "data_stats.json").read_text())["episodes"] == 3  # what it was fine-tuned on
    mine, shipped = (json.loads((d / "norm_stats.json").read_text()) for d in (m, pb.SHIPPED))
    assert all(mine[k] == v for k, v in shipped.items())  # fine-tuned in the shipped model's action units
    # sweep: real and online rollouts of both splits, and the report
    with tarfile.open(out / "sweep_store.tgz") as tar:
        recs = [json.loads(x) for x in tar.extractfile("results.jsonl").read().decode().splitlines()]
        assert "report/report.md" in tar.getnames()
        # the report says what the model was trained on, and that reverse bussing is never in that data
        md = tar.extractfile("report/report.md").read().decode()
        assert "The world model's training data. 3 episodes" in md and "never shows: reverse" in md
    assert {r["split"] for r in recs if r["mode"] == "online"} == {"in_distribution", "out_of_distribution"}
    assert sum(r["mode"] == "real" for r in recs) == 9 and sum(r["mode"] == "online" for r in recs) == 6
    # distill: the student, two steps from the shipped model, with what its teacher was trained on
    distill = json.loads((out / "distill.json").read_text())
    assert distill["step"] == 2 and not distill["trainer_running"]
    assert "loss_teacher_1step" in distill["last_metrics"][-1]
    parts = sorted(f for f in files if f.startswith("student_2.tgz"))
    (tmp_path / "s.tgz").write_bytes(b"".join((out / f).read_bytes() for f in parts))
    with tarfile.open(tmp_path / "s.tgz") as tar:
        tar.extractall(tmp_path / "student")
    s = tmp_path / "student" / "student_2"
    assert (s / "state_reader.npz").exists() and (s / "params.npz").exists()
    assert (s / "data_stats.json").read_bytes() == (pb.SHIPPED / "data_stats.json").read_bytes()
    # bench: its last line
    assert json.loads((out / "bench.json").read_text())["result"].startswith("accelerator cpu: train_mfu=")
    assert [x["phase"] for x in json.loads((run / "phases.json").read_text())] == list(pb.PHASES)
    # resumable: the data phase again writes nothing new
    p = subprocess.run(cmd[:3] + ["data"] + cmd[4:], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0 and '"skipped": 3' in (run / "logs" / "data.log").read_text()
