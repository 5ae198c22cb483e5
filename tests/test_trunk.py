"""A WSD trunk: warmed up once and held; its travelling state resumes as the unbroken run goes on (same losses, same
windows); a branch anneals a copy to ~0 and exports it; every export carries the lineage, continued by a resumed
run and by a branch."""
import dataclasses
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.core.config import Config, DataConfig, ModelConfig, TrainConfig
from sc3_jax.core.errors import UserError
from sc3_jax.data import synthetic
from sc3_jax.train import branch, lineage, trunk_state
from sc3_jax.train.train import check_schedule, lr_schedule, read_metrics, train, wsd_schedule

LR = 1e-3


def _cfg(data, workdir, steps, **train_kw) -> Config:
    return Config(model=ModelConfig(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                    rope_axes_dim=(2, 3, 3)),
                  data=DataConfig(path=str(data), image_size=(8, 8), context_frames=1, future_frames=2, batch_size=8),
                  train=TrainConfig(**{**dict(workdir=str(workdir), steps=steps, ckpt_every=4, log_every=1, lr=LR,
                                              warmup_steps=3, schedule="wsd", progress=False, tensorboard=False,
                                              async_checkpointing=False), **train_kw}))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("trunk") / "episodes"
    synthetic.generate(str(path), 6, length=30, image_size=(8, 8), seed=0, progress=False)
    return path


# ---- the schedule ------------------------------------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(warmup=st.integers(0, 500), held=st.integers(1, 5000), decay=st.integers(1, 2000), lr=st.floats(1e-6, 1e-1))
def test_wsd_warms_up_once_holds_the_peak_and_a_branch_decays_to_zero(warmup, held, decay, lr):
    trunk = wsd_schedule(lr, warmup, None, warmup + held)
    longer = wsd_schedule(lr, warmup, None, 10 * (warmup + held))
    if warmup:
        assert float(trunk(0)) == 0.0 and float(trunk(warmup // 2)) <= lr * 0.5 * (1 + 1e-6)  # float32 rates
    for s in (warmup, warmup + held // 2, warmup + held, 50 * (warmup + held)):
        assert float(trunk(s)) == pytest.approx(lr, rel=1e-6)  # held, however long the trunk goes on
        assert float(longer(s)) == float(trunk(s))  # the trunk's rates do not depend on where a stretch stops
    start = warmup + held
    b = wsd_schedule(lr, warmup, start, start + decay)
    assert float(b(start)) == pytest.approx(lr, rel=1e-6)
    rates = [float(b(s)) for s in range(start, start + decay + 1, max(1, decay // 20))]
    assert all(x >= y - 1e-12 for x, y in zip(rates, rates[1:]))  # falls monotonically
    assert float(b(start + decay)) == pytest.approx(0.0, abs=1e-12)
    last = lr * (1 - (1 - 1 / decay) ** 0.5)  # ~lr / (2 decay): ~0 at the branch's last update
    assert float(b(start + decay - 1)) == pytest.approx(last, rel=2e-3, abs=1e-9)


def test_a_wsd_run_without_a_peak_or_with_a_decay_outside_it_is_one_line():
    for t, words in [(TrainConfig(schedule="wsd", lr=0.0), "peak"),
                     (TrainConfig(schedule="wsd", lr=float("nan")), "peak"),
                     (TrainConfig(schedule="wsd", steps=100, decay_start=200), "decay_start"),
                     (TrainConfig(schedule="wsd", steps=100, warmup_steps=50, decay_start=10), "decay_start"),
                     (TrainConfig(schedule="cosine", decay_start=10), "wsd"),
                     (TrainConfig(schedule="linear"), "cosine, wsd")]:
        with pytest.raises(UserError, match=words) as e:
            check_schedule(t)
        assert "\n" not in str(e.value)
    # a trunk needs no end: its warm-up may be as long as a stretch (the peak is held after it, whatever follows)
    assert float(lr_schedule(TrainConfig(schedule="wsd", steps=10, warmup_steps=100, lr=1.0))(50)) == 0.5


def test_a_branch_longer_than_its_trunk_is_refused_in_one_line():
    with pytest.raises(UserError, match="--steps 40") as e:
        branch.check_branch(step=200, steps=201)
    assert "\n" not in str(e.value)
    branch.check_branch(step=200, steps=200)


# ---- the travelling state ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def unbroken(data, tmp_path_factory):
    work = tmp_path_factory.mktemp("unbroken") / "run"
    train(_cfg(data, work, 12))
    return work


@pytest.mark.parametrize("moments, rel", [("float32", 1e-6), ("bfloat16", 2e-3)])
def test_a_run_resumed_from_its_travelling_state_goes_on_as_the_unbroken_run(data, unbroken, tmp_path, moments, rel):
    first = tmp_path / "first"
    train(_cfg(data, first, 8))  # stopped at step 8 (a session's end)
    state = branch.save_run(first, tmp_path / "state", moments)
    meta = trunk_state.read_meta(state)
    assert meta["step"] == 8 and meta["moments"] == moments
    # a new machine: another directory, the state only
    second = tmp_path / "second"
    train(_cfg(data, second, 12, resume_from=str(state)))
    a, b = read_metrics(unbroken), read_metrics(second)
    assert sorted(b) == list(range(9, 13))
    for s in b:
        assert b[s]["loss"] == pytest.approx(a[s]["loss"], rel=rel), s
        assert b[s]["lr"] == pytest.approx(a[s]["lr"], rel=1e-6)
    # the same windows: the data iterator's position after step 12 is the unbroken run's
    end_a = trunk_state.read_meta(branch.save_run(unbroken, tmp_path / "end_a", moments))
    end_b = trunk_state.read_meta(branch.save_run(second, tmp_path / "end_b", moments))
    assert end_a["data"] == end_b["data"] and end_a["step"] == end_b["step"] == 12


def test_the_lineage_is_carried_by_a_resumed_run_and_by_a_branch(data, unbroken, tmp_path):
    lin = lineage.read(unbroken)
    assert lin["windows"] == 12 * 8 and len(lin["stretches"]) == 1
    assert lin["stretches"][0]["to_step"] == 12 and lin["stretches"][0]["schedule"] == "wsd"
    s0 = lin["stretches"][0]
    assert s0["commit"] and s0["wall_s"] > 0 and 0.5 * s0["wall_s"] <= s0["train_s"] <= s0["wall_s"] + 1e-6

    state = branch.save_run(unbroken, tmp_path / "state")
    assert lineage.read(state) == lin
    resumed = tmp_path / "resumed"
    train(_cfg(data, resumed, 16, resume_from=str(state)))
    lin2 = lineage.read(resumed)
    assert lin2["windows"] == 16 * 8 and [s["run"] for s in lin2["stretches"]] == ["run", "resumed"]
    assert "branch" not in lin2
    out, lin3 = branch.branch(resumed, 4, tmp_path / "branch_export", progress=False)
    assert lin3["windows"] == 20 * 8 and lin3["branch"] == {"decay_start": 16, "to_step": 20}
    assert [s["run"] for s in lin3["stretches"]][:2] == ["run", "resumed"]
    rows = read_metrics(tmp_path / "resumed_branch_s16_d4")
    assert [round(rows[s]["lr"] / LR, 6) for s in sorted(rows)] == [1.0, round(1 - 0.25 ** 0.5, 6),
                                                                    round(1 - 0.5 ** 0.5, 6),
                                                                    round(1 - 0.75 ** 0.5, 6)]
    assert json.loads((out / "lineage.json").read_text()) == lin3
    # the trunk itself is untouched: it goes on from step 16 at its peak
    assert lineage.read(resumed) == lin2 and max(read_metrics(resumed)) == 16

def test_the_clock_leaves_out_a_pause_and_keeps_the_training():
    clock = lineage.StepClock(0.0)
    for t in [30, 60, 90, 120, 1920, 1950, 1980]:  # a 30 s gap between syncs, one 30 min pause
        clock.tick(float(t))
    assert clock.wall_s(1980.0) == 1980 and clock.train_s == pytest.approx(7 * 30)


def test_a_travelling_state_whose_params_were_exported_over_is_refused(data, unbroken, tmp_path):
    state = branch.save_run(unbroken, tmp_path / "state")
    with np.load(state / "params.npz") as z:
        arrays = {k: z[k] for k in z.files}
    k = sorted(arrays)[0]
    arrays[k] = arrays[k] + 1
    np.savez(state / "params.npz", **arrays)
    with pytest.raises(UserError, match="export the state again"):
        trunk_state.read_meta(state)


def test_a_resume_with_another_config_is_refused_naming_the_field(data, unbroken, tmp_path):
    state = branch.save_run(unbroken, tmp_path / "state")
    cfg = _cfg(data, tmp_path / "other", 20, resume_from=str(state))
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, lr=2 * LR))
    with pytest.raises(UserError, match="train.lr"):
        train(cfg)


def test_sc3_trunk_refuses_what_is_not_a_trunk_in_one_line(data, unbroken, tmp_path):
    import subprocess
    import sys

    def run(*args):
        r = subprocess.run([sys.executable, "-m", "sc3_jax.cli", "trunk", *args], capture_output=True, text=True,
                           timeout=300)
        return r.returncode, r.stderr.strip()

    code, err = run("branch", "--trunk", str(tmp_path / "nothing"), "--steps", "2", "--out", str(tmp_path / "o"))
    assert code in (1, 2) and "no such trunk" in err and len(err.splitlines()) == 1, err
    code, err = run("branch", "--trunk", str(unbroken), "--steps", "13", "--out", str(tmp_path / "o"))
    assert code in (1, 2) and "--steps 2" in err and len(err.splitlines()) == 1, err
    cosine = tmp_path / "cosine"
    train(_cfg(data, cosine, 4, schedule="cosine", warmup_steps=1))
    code, err = run("branch", "--trunk", str(cosine), "--steps", "2", "--out", str(tmp_path / "o"))
    assert code in (1, 2) and "not a WSD trunk" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_the_learned_robot_state_travels_with_the_trunk(data, unbroken, tmp_path):
    # the head reads the robot's state from real frames and actions, not from the DiT: the continued model keeps it
    state = branch.save_run(unbroken, tmp_path / "state")
    (state / "state_head.npz").write_bytes(b"the head's bytes")
    resumed = tmp_path / "resumed"
    train(_cfg(data, resumed, 13, resume_from=str(state)))
    assert (resumed / "state_head.npz").read_bytes() == b"the head's bytes"
    again = branch.save_run(resumed, tmp_path / "again")
    assert (again / "state_head.npz").read_bytes() == b"the head's bytes"


def test_saving_a_live_trunks_state_leaves_the_checkpoint_it_is_writing_alone(unbroken, tmp_path):
    # a trunk's async checkpoint in progress is a temporary directory; a reader that cleaned it up killed the trunk
    live = unbroken / "checkpoints" / "99.orbax-checkpoint-tmp"
    (live / "state").mkdir(parents=True)
    (live / "state" / "being_written").write_text("x")
    try:
        branch.save_run(unbroken, tmp_path / "state")
        assert (live / "state" / "being_written").read_text() == "x"
    finally:
        import shutil
        shutil.rmtree(live)
