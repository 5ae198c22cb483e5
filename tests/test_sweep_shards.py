"""A sweep spread over processes: real rollouts in worker processes and disjoint shards in separate processes give
exactly the records of one process, and the report reads the shards as one store."""
import dataclasses
import json
import math
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import engine, report, report_bench_render
from sc3_jax.benchmarks.bussing import perception, sweep
from sc3_jax.evaluation.merged import open_store
from sc3_jax.evaluation.results import EVAL_MODES, ResultsStore, seed_blocks
from test_sweep import POLICIES, tiny_world_model


def by_id(store) -> dict:
    return {r["id"]: r for r in store.records()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny world model, perception weights and a sweep config over them (nothing run yet)."""
    root = tmp_path_factory.mktemp("shards")
    wm = tiny_world_model(root)
    perception.save(root / "perception.npz", perception.init(jax.random.key(1)))
    cfg = sweep.SweepConfig(out=str(root / "one"), world_model=str(wm), perception=str(root / "perception.npz"),
                            policies=POLICIES, episodes=3, episode_seconds=1.6, batch=2, progress=False,
                            taus=(math.inf, 1.0), calibration_episodes=1, ceiling_episodes=1, modes=EVAL_MODES,
                            workers=1)
    return root, cfg


@pytest.fixture(scope="module")
def setup(tiny):
    """The unsharded sweep, in one process, the reference the spread-out runs must reproduce."""
    sweep.run_sweep(tiny[1])
    return tiny


def test_work_units_split_into_disjoint_shards_that_cover_the_sweep(tiny):
    _, cfg = tiny
    units = engine.work_units(len(POLICIES), seed_blocks(cfg), cfg.modes, cfg.batch)
    shares = [units[i::3] for i in range(3)]
    assert sorted(map(repr, sum(shares, []))) == sorted(map(repr, units))
    # every (policy, seed, mode) exactly once; a batch of 3 evaluation seeds at batch 2 is two units
    work = [(u.policy, s, m) for u in units for s in u.seeds for m in ["real"] * u.real + [m for m, _ in u.modes]]
    assert len(work) == len(set(work)) == len(POLICIES) * (5 + 3 + 4)
    assert [u.seeds for u in units if u.policy == 0 and u.block == "evaluation"] == [(10_000_000, 10_000_001),
                                                                                     (10_000_002,)]
    for bad in ("2/2", "1", "a/b", "-1/2"):
        with pytest.raises(ValueError, match="I/N"):
            engine.parse_shard(bad)


@pytest.mark.slow  # ~2 min: an unsharded sweep, then worker processes that each import JAX and compile
def test_rollouts_in_two_worker_processes_equal_one_process(setup, tmp_path):
    """Real rollouts and world-model batches (offline, online) in 2 single-threaded worker processes: the records
    and arrays of the sweep run in one process (multi-threaded), bit for bit."""
    _, cfg = setup
    out = sweep.run_sweep(dataclasses.replace(cfg, out=str(tmp_path / "two"), workers=2))
    two, one = ResultsStore(out), ResultsStore(cfg.out)
    assert by_id(two) == by_id(one) and {r["mode"] for r in two.records()} == set(EVAL_MODES)
    assert [r["id"] for r in two.records()] == [r["id"] for r in one.records()]  # appended in the same order
    for rid in by_id(one):
        with np.load(two.array_path(rid)) as a, np.load(one.array_path(rid)) as b:
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files), rid
    timing = json.loads((out / "timing.json").read_text())
    assert timing["workers"] == timing["model_workers"] == 2
    assert sum(timing["rollouts_run"].values()) == len(by_id(two))
    assert 0 < timing["share_in_world_model_calls"] < 1  # both workers' compiled calls, over both workers' time


@pytest.mark.slow  # ~2 min: two sweep processes beside the unsharded one
def test_two_shard_processes_merge_into_the_unsharded_sweep(setup, tmp_path):
    root, cfg = setup
    out = tmp_path / "sharded"
    procs = []
    for i in range(2):
        code = ("import math; import sc3_jax.benchmarks.bussing; from sc3_jax.benchmarks.bussing import sweep; "
                f"sweep.run_sweep(sweep.SweepConfig(out={str(out)!r}, world_model={cfg.world_model!r}, "
                f"perception={cfg.perception!r}, policies={POLICIES!r}, episodes=3, episode_seconds=1.6, batch=2, "
                "progress=False, taus=(math.inf, 1.0), calibration_episodes=1, ceiling_episodes=1, workers=1, "
                f"modes=('real', 'offline', 'online'), shard='{i}/2'))")
        procs.append(subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ), stderr=subprocess.PIPE))
    for p in procs:
        assert p.wait(timeout=600) == 0, p.stderr.read().decode()[-2000:]
    shards = [ResultsStore(out / f"shard-{i}-of-2") for i in range(2)]
    assert all(s.records() for s in shards) and not set(by_id(shards[0])) & set(by_id(shards[1]))
    merged = open_store(out)
    assert by_id(merged) == by_id(ResultsStore(cfg.out))
    # the report of the shards is the report of the unsharded store, number for number
    a, b = report.compute(out), report.compute(cfg.out)
    for t in (a, b):
        t["config"].pop("out"), t["config"].pop("shard", None), t.pop("read_from")
    assert json.loads(json.dumps(a)) == json.loads(json.dumps(b))
    # a shard resumes as itself: rerunning shard 0 finds its work done and leaves its records as they were
    before = shards[0].path.read_bytes()
    sweep.run_sweep(dataclasses.replace(cfg, out=str(out), shard="0/2"))
    assert shards[0].path.read_bytes() == before


def test_stores_of_different_sweeps_do_not_merge(tiny, tmp_path):
    _, cfg = tiny
    a, b, c = (tmp_path / n for n in "abc")
    ResultsStore(a, dict(cfg.to_json(), shard="0/2"))
    ResultsStore(b, dict(dataclasses.replace(cfg, episodes=1).to_json(), shard="1/2"))
    with pytest.raises(ValueError, match="not shares of one sweep .*episodes"):
        open_store([a, b])
    ResultsStore(c, dict(cfg.to_json(), shard="1/2"))
    for store, rid in ((a, "p/1_real"), (c, "p/1_real")):  # the same rollout in two shares
        ResultsStore(store).append([{"id": rid, "mode": "real"}])
    with pytest.raises(ValueError, match="in both"):
        open_store([a, c])
    with pytest.raises(UserError, match="not a results store"):  # a one-line error for `sc3 report WRONG_DIR`
        open_store(tmp_path / "nothing_here")


def test_report_warns_on_a_one_policy_split_and_names_what_it_read(tiny, tmp_path):
    import shutil
    _, cfg = tiny
    out = sweep.run_sweep(dataclasses.replace(cfg, out=str(tmp_path / "one_policy"), modes=("real",),
                                              policies=POLICIES[:1], episodes=2, calibration_episodes=0,
                                              ceiling_episodes=0, workers=1))
    moved = tmp_path / "archived"
    moved.mkdir()
    for f in ("sweep.json", "results.jsonl"):  # an archived store: no rollouts/, read from elsewhere
        shutil.copy(out / f, moved / f)
    text = report.render(moved, tmp_path / "rep", videos=2).read_text()
    assert f"Results: `{moved.name}`" in text and str(tmp_path) not in text  # named, not this machine's path
    assert "in_distribution: one policy only" in text and "out_of_distribution: one policy" not in text
    assert "No videos" in text


def test_verdict_says_better_than_a_guess_only_when_the_paired_interval_excludes_0():
    cell = lambda v, lo, hi: {"value": v, "lo": lo, "hi": hi}  # noqa: E731
    t = {"faithfulness": {"physics": {"online": {
        "splits": {"in_distribution": {"pearson": cell(0.8, 0.7, 0.9)},
                   "out_of_distribution": {"pearson": cell(0.7, 0.6, 0.8)},
                   "overall": {"pearson": cell(0.7, 0.6, 0.8)}},
        "vs_floor": {"in_distribution": {"pearson": cell(0.1, 0.02, 0.2), "mmrv": cell(-0.1, -0.2, 0.01)},
                     "out_of_distribution": {"pearson": cell(0.0, -0.1, 0.1), "mmrv": cell(0.0, -0.1, 0.1)},
                     "overall": {"pearson": cell(0.0, -0.1, 0.1), "mmrv": cell(-0.1, -0.2, -0.01)}}}}}}
    lines = report_bench_render.verdict(t)
    assert "better than a policy-blind guess on r" in lines[0] and "MMRV" not in lines[0].split("on r")[-1]
    assert "not distinguishable" in lines[1] and "better than a policy-blind guess on MMRV" in lines[2]
