"""launch/gpu_playbook.py: its dry run takes every phase (SO-101 data and training, mixture, fine-tune of the
shipped model, sweep, 1-step student, bench) through on the CPU and leaves what a device call may bring back; its
sweep runs the archived store's protocol; its exports fit a call's return and its deadlines stop whole process
groups."""
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


def tiny_so101_start(root: Path) -> Path:
    """A stand-in for the committed SO-101 CPU export: ``so101_latent``'s recipe on two 16 x 16 cameras, pixel
    patches instead of the learned tokenizer (none to train), a one-layer model at initialisation."""
    import jax
    import numpy as np

    from sc3_jax.model import checkpoint
    from sc3_jax.train import train
    from sc3_jax.benchmarks.so101.collect import action_space
    from sc3_jax.core.config import load_config, replace
    from sc3_jax.data.action_space import ActionSpace
    from sc3_jax.data.norm_stats import NormStats

    cfg = replace(load_config("so101_latent"), data=dict(views=("workspace", "wrist"), image_size=(16, 16)),
                  model=dict(tokenizer="pixel", tokenizer_path=None, dim=32, depth=1, num_heads=2, num_kv_heads=1,
                             head_dim=16, mlp_dim=64, rope_axes_dim=(4, 2, 2), num_views=2, action_dim=4))
    stats = NormStats(np.zeros(4), np.ones(4), action_space=ActionSpace.from_dict(action_space()))
    out = checkpoint.save(root / "so101_start", cfg, stats, jax.device_get(train.init_state(cfg)["params"]),
                          np.float32)
    (out / "state_head.npz").write_bytes(b"the start's head")  # copied, never read by the phase
    (out / "detector").mkdir()
    (out / "detector" / "detector.json").write_text("{}")
    return out


def test_so101_trains_the_cpu_export_in_its_own_config_at_batch_64(tmp_path):
    start = tiny_so101_start(tmp_path)
    ctx = pb.Ctx(pb.Args("so101", run=str(tmp_path), so101_from=str(start)), tmp_path, tmp_path, 0.0)
    steps, batch = pb._train_target(ctx, "so101")
    assert (steps, batch) == (4000, 64)
    cmd = pb._trainer_cmd(ctx, steps, "so101")
    opt = {k: cmd[cmd.index(k) + 1] for k in ("--train.init-from", "--batch", "--data",
                                                "--train.workdir")}
    assert opt == {"--train.init-from": str(start), "--batch": "64",
                   "--data": str(tmp_path / "so101_data" / "train"), "--train.workdir": str(tmp_path / "so101")}
    assert "--train.lr" not in cmd  # the start's own schedule: it is far from trained
    from sc3_jax.core.config import load_config
    assert load_config(cmd[cmd.index("--config") + 1]).model.dim == 32  # the start's config, not so101_latent's
    flags = [c for c in cmd if c.startswith("--")]
    assert len(flags) == len(set(flags)), "an option given twice"
    # no start: one line naming it, before anything runs
    with pytest.raises(SystemExit, match=r"--so101-from .*nowhere: no exported model there"):
        pb.so101_from(pb.Args("so101", so101_from=str(tmp_path / "nowhere")))


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


def dry_run(tmp_path: Path, phase: str, timeout: int) -> tuple[subprocess.CompletedProcess, list[str]]:
    """``--phase PHASE --dry-run`` from a tiny SO-101 start, in ``tmp_path``/run and /out; its command."""
    start = tmp_path / "so101_start"
    if not start.exists():
        tiny_so101_start(tmp_path)
    cmd = [sys.executable, str(ROOT / "launch" / "gpu_playbook.py"), "--phase", phase, "--dry-run", "--run",
           str(tmp_path / "run"), "--out", str(tmp_path / "out"), "--so101-from", str(start)]
    return playbook(cmd, timeout), cmd


def playbook(cmd: list[str], timeout: int) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    # one CPU device, as on a user's machine (the test session forces 8 for the sharding tests)
    env["XLA_FLAGS"] = re.sub(r"--xla_force_host_platform_device_count=\d+", "", env.get("XLA_FLAGS", ""))
    p = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def unpack(out: Path, name: str, to: Path) -> Path:
    """``OUT/name.tgz[.NN]`` joined (`cat name.tgz* | tar xz`) and unpacked into ``to``; returns ``to``."""
    parts = sorted(f for f in out.iterdir() if f.name.startswith(f"{name}.tgz"))
    to.mkdir()
    (to / f"{name}.tgz").write_bytes(b"".join(f.read_bytes() for f in parts))
    with tarfile.open(to / f"{name}.tgz") as tar:
        tar.extractall(to)
    return to


@pytest.mark.slow
def test_the_so101_dry_run_collects_trains_the_start_and_exports_it(tmp_path):
    p, cmd = dry_run(tmp_path, "so101", 900)
    run, out = tmp_path / "run", tmp_path / "out"
    res = json.loads((out / "so101.json").read_text())
    assert {k: v["n"] for k, v in res["data"]["splits"].items()} == {"train": 2, "heldout": 1}
    assert res["step"] == 2 and res["windows"] == 4 and not res["trainer_running"]
    assert len(res["exports"]) + 1 <= 8 and all((out / f).exists() for f in res["exports"])
    assert all(NAME.match(f.name) and f.stat().st_size <= 16 * 2**20 for f in out.iterdir())
    # collected at the start's cameras and size; trained from it at its config, in its action units
    collect = json.loads((out / "so101_collect.json").read_text())
    assert collect["views"] == ["workspace", "wrist"] and collect["image_size"] == [16, 16]
    m = unpack(out, "so101_2", tmp_path / "so101") / "so101_2"
    start = tmp_path / "so101_start"
    cfg = json.loads((m / "config.json").read_text())
    assert cfg["model"]["dim"] == 32 and cfg["data"]["views"] == ["workspace", "wrist"]
    # in the start's action units; a start whose pose integrated the commands from zero (this one) is conditioned on
    # the measured entries they move from then on (train.reconditioned), the committed exports keep their own
    mine, theirs = (json.loads((d / "norm_stats.json").read_text()) for d in (m, start))
    assert mine["mean"] == theirs["mean"] and mine["std"] == theirs["std"]
    assert {k: mine["action_space"][k] for k in theirs["action_space"]} == theirs["action_space"]
    assert len(mine["action_space"]["measured"]) == 4 and mine["action_space"]["measured"][3] == -1
    # the start's detector; the trainer reached its last step, so the state head is its own, fitted on the new data
    assert (m / "detector" / "detector.json").exists() and (m / "state_head.npz").read_bytes() != b"the start's head"
    # again: the data is there, the trainer done, the export shipped: nothing runs twice
    p = playbook(cmd, 600)
    assert (run / "logs" / "so101_data.log").read_text().count("so101 collect") == 1
    assert "trainer started" not in p.stdout and len(list(out.glob("so101_2.tgz*"))) >= 1


@pytest.mark.slow
def test_the_dry_run_takes_every_phase_through_on_the_cpu(tmp_path):
    p, cmd = dry_run(tmp_path, "all", 1800)
    run, out = tmp_path / "run", tmp_path / "out"
    for phase in pb.PHASES:
        assert f"== phase {phase}" in p.stdout
    assert re.search(r"device minutes per phase so far: so101 [\d.]+, data [\d.]+, train [\d.]+, sweep [\d.]+, "
                     r"distill [\d.]+, bench [\d.]+; ", p.stdout)
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
    m = unpack(out, "model_2", tmp_path / "model") / "export_2"
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
    s = unpack(out, "student_2", tmp_path / "student") / "student_2"
    assert (s / "state_reader.npz").exists() and (s / "params.npz").exists()
    assert (s / "data_stats.json").read_bytes() == (pb.SHIPPED / "data_stats.json").read_bytes()
    # bench: its last line
    assert json.loads((out / "bench.json").read_text())["result"].startswith("accelerator cpu: train_mfu=")
    assert [x["phase"] for x in json.loads((run / "phases.json").read_text())] == list(pb.PHASES)
    assert json.loads((out / "so101.json").read_text())["step"] == 2  # the rest: the so101 test
    # resumable: the data phase again writes nothing new
    playbook(cmd[:3] + ["data"] + cmd[4:], 600)
    assert '"skipped": 3' in (run / "logs" / "data.log").read_text()
