"""The failure-rich mixture (benchmarks/bussing/mixture.py): its data-collection policies are not the evaluated zoo, it never holds
the reverse task or an every-object swap, it is deterministic per (seed, episode) whatever the sharding, its
failure modes happen, and its outcome categories read the same from demo stores and sweep records."""
from __future__ import annotations

import json

import numpy as np

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.benchmarks.bussing import mixture as M
from sc3_jax.benchmarks.bussing.env import BussingEnv
from sc3_jax.benchmarks.bussing.tasks import make_initial_condition
from sc3_jax.benchmarks.bussing.zoo import ZOO


def test_no_data_collection_source_is_an_evaluated_zoo_policy():
    assert set(M.SOURCES).isdisjoint(ZOO)
    for recipe in M.RECIPES.values():
        assert set(recipe) <= set(M.SOURCES)
    # the controller source reads the simulator's state through an estimation error of its own, never a learned
    # estimator (the zoo's checkpoints); its knobs are drawn per episode
    draws = [M.draw("dc_controller", np.random.default_rng(i), ("cup", "bag", "lid")) for i in range(200)]
    assert all(k["bias"] > 0 for k in draws) and len({json.dumps(k, sort_keys=True) for k in draws}) == 200


def test_the_mixture_writes_bussing_only_without_loading_any_zoo_policy(tmp_path, monkeypatch):
    from sc3_jax.benchmarks.bussing import zoo

    def refuse(*a, **k):
        raise AssertionError("a data-collection policy loaded zoo weights")
    monkeypatch.setattr(zoo, "load_policy", refuse)
    monkeypatch.setattr(zoo, "load_params", refuse)
    first = {}  # the first episode of each source under the failure_rich recipe, seed 7
    for i in range(100):
        first.setdefault(M.choose_source("failure_rich", 7, i)[0], i)
    assert set(first) == set(M.SOURCES)
    n = max(first.values()) + 1
    for i in first.values():  # shard (i, 1000) of n < 1000 episodes: episode i alone
        res = M.generate_mixture(tmp_path / "mix", n, seed=7, image_size=(16, 16), shard=(i, 1000), progress=False)
        assert res["written"] == 1 and res["rejected"] == 0
    metas = [json.loads(p.read_text()) for p in sorted((tmp_path / "mix").glob("ep*/meta.json"))]
    assert {m["source"] for m in metas} == set(M.SOURCES)
    for m in metas:
        assert m["task"] == "bussing" and "policy" not in m and m["recipe"] == "failure_rich"
        assert m["prompt"] == make_initial_condition(m["sim_seed"], "bussing").prompt  # never the reverse one
        assert m["outcome"] == M.outcome_counts(m["labels"]["objects"])
        assert sum(not o["language"] for o in m["labels"]["objects"]) < len(m["labels"]["objects"])


def test_every_object_in_the_other_container_is_refused(tmp_path, monkeypatch):
    from sc3_jax.benchmarks.bussing.expert import run_expert_episode

    def all_wrong(env, source, knobs, sim_seed, record=True):
        r = run_expert_episode(env, sim_seed, "bussing", record=record)
        r.outcomes = [o.__class__(**{**o.to_json(), "language": False, "outcome": "language"}) for o in r.outcomes]
        return r, {}
    monkeypatch.setattr(M, "run_source", all_wrong)
    res = M.generate_mixture(tmp_path / "mix", 1, seed=7, image_size=(16, 16), progress=False)
    assert res["written"] == 0 and res["rejected"] == 1 and res["rejected_episodes"] == ["ep0700000"]
    assert not list((tmp_path / "mix").glob("ep*"))


def test_at_most_one_object_is_planned_for_the_other_container():
    for source in ("dc_expert", "dc_controller"):
        wrongs = [M.draw(source, np.random.default_rng(i), ("cup", "bag", "lid"))["wrong"] for i in range(300)]
        assert 0.3 < np.mean([w is not None for w in wrongs]) < 0.7  # single wrong carries do occur
        assert all(w in (None, "cup", "bag", "lid") for w in wrongs)
        # a single object in the other container would be every object: never planned
        assert all(M.draw(source, np.random.default_rng(i), ("cup",))["wrong"] is None for i in range(100))


def test_sources_and_draws_depend_on_seed_and_episode_only():
    a = [M.choose_source("failure_rich", 40, i) for i in range(50)]
    b = [M.choose_source("failure_rich", 40, i) for i in reversed(range(50))][::-1]
    assert [s for s, _ in a] == [s for s, _ in b]
    assert [M.draw(s, r, ("cup", "bag")) for s, r in a] == [M.draw(s, r, ("cup", "bag")) for s, r in b]
    counts = {s: sum(x == s for x, _ in (M.choose_source("failure_rich", 40, i) for i in range(2000)))
              for s in M.SOURCES}
    assert all(350 < c < 650 for c in counts.values()), counts  # a quarter each
    assert {M.choose_source("clean", 40, i)[0] for i in range(50)} == {"expert_clean"}


def test_sharded_writes_equal_one_write(tmp_path):
    M.generate_mixture(tmp_path / "one", 2, seed=7, image_size=(16, 16), progress=False)
    for i in range(2):
        M.generate_mixture(tmp_path / "two", 2, seed=7, image_size=(16, 16), shard=(i, 2), progress=False)
    eps = sorted(p.name for p in (tmp_path / "one").glob("ep*"))
    assert eps == sorted(p.name for p in (tmp_path / "two").glob("ep*")) and len(eps) == 2
    for e in eps:
        assert (tmp_path / "one" / e / "meta.json").read_text() == (tmp_path / "two" / e / "meta.json").read_text()
        assert np.array_equal(np.load(tmp_path / "one" / e / "actions.npy"), np.load(tmp_path / "two" / e /
                                                                                       "actions.npy"))
    res = M.generate_mixture(tmp_path / "one", 2, seed=7, image_size=(16, 16), progress=False)
    assert res["written"] == 0 and res["skipped"] == 2  # resumable


def test_the_data_collection_expert_retries_and_drops():
    from sc3_jax.benchmarks.bussing.expert import ExpertKnobs, run_expert_episode
    env = BussingEnv(render=False)
    seed = 4_000_003
    objects = make_initial_condition(seed, "bussing", 3).objects
    # every first grasp misses by 5 cm; a retry aims well (retry_sigma 0): the objects get lifted after all
    dc = M.DataCollectionExpert(ExpertKnobs(), seed, attempts=3, retry_sigma=0.0)
    r = _run_missing_first(env, seed, dc)
    assert dc.events["retries"] >= 2 and sum(o.lifting for o in r.outcomes) >= 2
    once = M.DataCollectionExpert(ExpertKnobs(), seed, attempts=1)  # the same without retries: all missed
    r1 = _run_missing_first(env, seed, once)
    assert once.events["retries"] == 0 and not any(o.lifting for o in r1.outcomes)
    # weak grasps: every object slips during its carry -> lifted, never placed
    drop = M.DataCollectionExpert(ExpertKnobs(), seed, drops=tuple(objects), drop_after=2)
    r2 = run_expert_episode(env, seed, "bussing", record=False, expert=drop)
    env.close()
    assert drop.events["drops"] == 3 and all(o.lifting and not o.placing for o in r2.outcomes)


def _run_missing_first(env, seed, expert):
    """run_expert_episode with every object's first grasp aimed 5 cm off (set after the expert's own reset)."""
    from sc3_jax.benchmarks.bussing.expert import run_expert_episode
    reset = expert.reset

    def reset_then_offset(e):
        reset(e)
        for p in expert.plans:
            p.grasp_offset = np.array([0.05, 0.0])
    expert.reset = reset_then_offset
    return run_expert_episode(env, seed, "bussing", record=False, expert=expert)


def test_the_state_controller_takes_its_wrong_object_to_the_other_container():
    from sc3_jax.benchmarks.bussing.policy_eval import run_policy_episode
    from sc3_jax.benchmarks.bussing.zoo import ControlKnobs
    env = BussingEnv(image_size=(16, 16))
    seed = 4_000_001
    wrong = make_initial_condition(seed, "bussing", 3).objects[0]
    host = M.StateController(env, ControlKnobs(), seed, bias=0.002, jitter=0.0, wrong=wrong)
    r = run_policy_episode(env, host, seed, "bussing", record=False, max_steps=400)
    env.close()
    by = {o.name: o for o in r.outcomes}
    assert not by[wrong].language and by[wrong].lifting
    assert all(o.language for n, o in by.items() if n != wrong) and host.chunks > 3


def test_outcome_categories_partition_the_objects():
    objs = [{"language": False, "lifting": True, "placing": False}, {"language": True, "lifting": False,
                                                                     "placing": False},
            {"language": True, "lifting": True, "placing": False}, {"language": True, "lifting": True, "placing": True}]
    assert [M.object_category(o) for o in objs] == ["wrong_container", "missed", "dropped", "placed"]
    c = M.outcome_counts(objs)
    assert c == {"lifted": 3, "placed": 1, "wrong_container": 1, "dropped": 1, "missed": 1, "objects": 4}
    assert sum(M.rates(c)[k] for k in ("placed", "wrong_container", "dropped", "missed")) == 1.0


def test_the_zoo_real_outcomes_read_the_archived_sweep():
    z = M.zoo_real_outcomes()
    assert z["conditions"] == 72 and set(z["policies"]) == set(ZOO)
    assert all(c["episodes"] == 72 and c["objects"] == 216 for c in z["policies"].values())
    assert z["tasks"]["bussing"]["objects"] == 7 * 216
    r = {n: M.rates(c) for n, c in z["policies"].items()}
    # docs/results.md, 72 conditions: bus_confused language 0.59 (0.41 wrong), bus_bc_small lifting 0.17
    assert round(r["bus_confused"]["wrong_container"], 2) == 0.41 and round(r["bus_bc_small"]["lifted"], 2) == 0.17
