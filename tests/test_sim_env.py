"""Simulator, expert, knobs, determinism, demos and zoo policies (fast: ~1 min on 2 CPU cores)."""
import json

import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before MuJoCo is imported)

pytest.importorskip("mujoco")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from sc3_jax.data.episodes import EpisodeStore  # noqa: E402
from sc3_jax.policies.base import JaxPolicy, as_host  # noqa: E402
from sc3_jax.benchmarks.bussing import zoo  # noqa: E402
from sc3_jax.benchmarks.bussing.criteria import success_rates  # noqa: E402
from sc3_jax.benchmarks.bussing.demos import generate_demos  # noqa: E402
from sc3_jax.benchmarks.bussing.env import BussingEnv  # noqa: E402
from sc3_jax.benchmarks.bussing.policy_eval import run_policy_episode  # noqa: E402
from sc3_jax.benchmarks.bussing.expert import ExpertKnobs, run_expert_episode  # noqa: E402
from sc3_jax.benchmarks.bussing.scene import OPEN_WIDTH  # noqa: E402


@pytest.fixture(scope="module")
def env():
    e = BussingEnv(render=False)
    yield e
    e.close()


@pytest.fixture(scope="module")
def renv():
    e = BussingEnv(image_size=(64, 64))
    yield e
    e.close()


def _rates(env, task, knobs, seeds):
    outs = []
    for s in seeds:
        outs += run_expert_episode(env, s, task, knobs, record=False).outcomes
    return success_rates(outs)


@pytest.mark.parametrize("task", ["bussing", "reverse"])
def test_expert_succeeds(env, task):
    r = _rates(env, task, ExpertKnobs(), range(100, 106))
    assert r["outcome/no failure"] >= 0.9, r


def test_control_at_10hz():
    e = BussingEnv(render=False, control_hz=10)
    r = run_expert_episode(e, 3, "bussing", record=False)
    assert e.substeps == 50 and r.length <= 200
    assert success_rates(r.outcomes)["outcome/no failure"] == 1.0


def test_knobs_produce_their_failure_category(env):
    seeds = range(200, 206)
    grasp = _rates(env, "bussing", ExpertKnobs(grasp_noise=0.05), seeds)
    assert grasp["outcome/lifting"] >= 0.4 and grasp["outcome/language"] == 0.0, grasp
    release = _rates(env, "bussing", ExpertKnobs(release_noise=0.1), seeds)
    assert release["outcome/placing"] >= 0.3 and release["lifting"] == 1.0, release
    wrong = _rates(env, "bussing", ExpertKnobs(wrong_destination_prob=1.0, never_swap_all=False), seeds)
    assert wrong["outcome/language"] == 1.0, wrong
    # by default one object per episode stays right: no episode is a reverse-bussing episode
    wrong = _rates(env, "bussing", ExpertKnobs(wrong_destination_prob=1.0), seeds)
    assert abs(wrong["outcome/language"] - 2 / 3) < 1e-9 and wrong["outcome/no failure"] > 0.3, wrong
    noisy = _rates(env, "bussing", ExpertKnobs(action_noise=0.015), seeds)
    assert noisy["outcome/no failure"] < 0.9, noisy


def test_action_interface_and_pose(env):
    env.reset(1, "bussing")
    p0 = env.ee_pose()
    assert p0.shape == (7,) and abs(p0[6] - OPEN_WIDTH) < 1e-3
    env.step(np.array([0.02, -0.01, 0.0, 0, 0, 0.1, OPEN_WIDTH]))
    p1 = env.ee_pose()
    np.testing.assert_allclose(p1[:3] - p0[:3], [0.02, -0.01, 0.0], atol=1e-6)
    np.testing.assert_allclose(p1[3:6], [0, 0, 0.1], atol=1e-6)
    env.step(np.array([1.0, 0, 0, 0, 0, 0, 0.0]))  # clipped to MAX_STEP, gripper closes on nothing
    p2 = env.ee_pose()
    assert np.linalg.norm(p2[:3] - p1[:3]) <= 0.04 + 1e-6 and p2[6] < 0.01


def test_determinism_same_seed_same_frames_and_outcomes(renv):
    a = run_expert_episode(renv, 7, "bussing", ExpertKnobs(action_noise=0.005), record=True, max_steps=60)
    b = run_expert_episode(renv, 7, "bussing", ExpertKnobs(action_noise=0.005), record=True, max_steps=60)
    for v in renv.views:
        assert a.frames[v].shape == (60, 64, 64, 3)
        np.testing.assert_array_equal(a.frames[v], b.frames[v])
    np.testing.assert_array_equal(a.actions, b.actions)
    assert [o.to_json() for o in a.outcomes] == [o.to_json() for o in b.outcomes]
    c = run_expert_episode(renv, 8, "bussing", ExpertKnobs(action_noise=0.005), record=True, max_steps=60)
    assert not np.array_equal(a.frames["left"], c.frames["left"])


def test_views_see_manipulation(renv):
    r = run_expert_episode(renv, 3, "bussing", record=True)
    for v in renv.views:
        f = r.frames[v].astype(np.int16)
        changed = np.mean(np.any(np.abs(f - f[:1]).max(-1) > 20, axis=0))
        assert changed > 0.05, (v, changed)  # gripper and objects cover a meaningful share of pixels


def test_any_resolution():
    e = BussingEnv(image_size=(48, 80))
    obs = e.reset(0)
    assert obs["images"].shape == (3, 48, 80, 3) and obs["images"].dtype == np.uint8
    assert obs["images"].std() > 10
    e.close()


def test_demos_written_resumable_and_bussing_only(tmp_path):
    s1 = generate_demos(tmp_path / "d", 2, seed=3, image_size=(32, 32), progress=False)
    assert s1["written"] == 2
    s2 = generate_demos(tmp_path / "d", 3, seed=3, image_size=(32, 32), progress=False)
    assert s2["written"] == 1 and s2["skipped"] == 2
    store = EpisodeStore(tmp_path / "d")
    assert store.views == ["left", "right", "wrist"] and len(store) == 3
    ep = store.load(store.episode_ids()[0])
    assert ep.frames["wrist"].shape[1:] == (32, 32, 3) and ep.actions.shape == (ep.length, 7)
    assert ep.prompt and ep.meta["task"] == "bussing" and len(ep.meta["labels"]["objects"]) == 3
    assert len(ep.meta["intent"]["obj_xy"]) == ep.length and len(ep.meta["intent"]["obj_xy"][0]) == 6
    # pseudo-actions: consecutive poses move by the (clipped) commanded translation
    np.testing.assert_allclose(np.diff(ep.ee_pose[:, :3], axis=0)[:5], ep.actions[:5, :3], atol=1e-4)
    with pytest.raises(ValueError):
        generate_demos(tmp_path / "r", 1, task="reverse", progress=False)


def test_policy_demos_record_the_zoo_policy_and_refuse_reverse_policies(tmp_path):
    """World-model data from a bussing zoo policy: the same episode as the sweep's real rollout of that seed."""
    s = generate_demos(tmp_path / "p", 1, seed=7, policy="bus_bc_small", progress=False)
    assert s["written"] == 1
    store = EpisodeStore(tmp_path / "p")
    ep = store.load(store.episode_ids()[0])
    assert ep.meta["policy"] == "bus_bc_small" and "knobs" not in ep.meta and ep.meta["sim_seed"] == 700_000
    env = BussingEnv(image_size=(64, 64))
    r = run_policy_episode(env, zoo.load_policy("bus_bc_small"), 700_000, "bussing")
    env.close()
    np.testing.assert_array_equal(ep.actions, r.actions)
    np.testing.assert_array_equal(ep.frames["left"], r.frames["left"])
    assert ep.meta["labels"]["objects"] == [o.to_json() for o in r.outcomes]
    for bad in ("rev_bc_full", "nope"):
        with pytest.raises(ValueError, match="choose a bussing zoo policy"):
            generate_demos(tmp_path / "q", 1, policy=bad, progress=False)


def test_controller_routes_by_task():
    obj_xy = jnp.zeros((zoo.N_OBJ, 2)).at[0].set(jnp.array([-0.1, 0.0])).at[1].set(jnp.array([-0.2, 0.1]))
    present = jnp.full((zoo.N_OBJ,), -3.0).at[0].set(3.0)
    est = {"obj_xy": obj_xy, "present": present, "dest": jnp.full((zoo.N_OBJ,), -3.0), "held_dest": jnp.array(3.0),
           "bin_xy": jnp.array([0.2, -0.13]), "can_xy": jnp.array([0.2, 0.13])}
    holding = jnp.array([0.0, 0.0, 0.17, 0, 0, 0, 0.05])  # a held object keeps the fingers apart
    a0 = zoo.controller(est, holding, jnp.int32(0))
    a1 = zoo.controller(est, holding, jnp.int32(1))
    assert a0.shape == (25, 7)
    assert float(jnp.sum(a0[:10, 1])) > 0.1 and float(jnp.sum(a1[:10, 1])) < -0.1  # can (+y) vs bin (-y)
    assert float(a0[:10, 6].max()) == 0.0 and abs(float(a0[:, 6].max()) - OPEN_WIDTH) < 1e-6  # carries, then releases
    empty_open = jnp.array([0.0, 0.0, 0.13, 0, 0, 0, OPEN_WIDTH])
    a = zoo.controller(est, empty_open, jnp.int32(0))
    assert float(jnp.sum(a[:6, 0])) < -0.09  # goes to pick the object at x = -0.1
    assert float(a[:, 6].min()) == 0.0  # and closes on it within the chunk


@pytest.mark.skipif(not (zoo.ZOO_DIR / "run_clean_final.npz").exists(), reason="zoo weights not trained")
def test_zoo_policies_are_pure_jax_and_host_usable(renv):
    assert len(zoo.zoo_names("bussing")) >= 4 and len(zoo.zoo_names("reverse")) >= 3
    obs = renv.reset(0)
    jobs = {k: jnp.asarray(obs[k]) for k in ("images", "state", "task")}
    for name in zoo.zoo_names():
        pol = zoo.load_policy(name)
        assert isinstance(pol, JaxPolicy) and pol.chunk == 25
        a = jax.jit(pol.apply)(pol.params, jobs, jax.random.key(0))
        assert a.shape == (25, 7) and bool(jnp.all(jnp.isfinite(a)))
    pol = zoo.load_policy("bus_bc_full")
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), jobs)
    av = jax.vmap(pol.apply, in_axes=(None, 0, None))(pol.params, batch, jax.random.key(0))

    def body(c, _):
        return c, pol.apply(pol.params, jobs, jax.random.key(0))
    _, ascan = jax.lax.scan(body, 0, None, length=2)
    np.testing.assert_allclose(av[0], ascan[0], atol=1e-5)
    host = as_host(pol)
    np.testing.assert_allclose(host.infer({k: obs[k] for k in ("images", "state", "task")}), av[0], atol=1e-5)
    r1 = run_policy_episode(renv, pol, 10_000_000, "bussing", max_steps=48, record=False)
    r2 = run_policy_episode(renv, pol, 10_000_000, "bussing", max_steps=48, record=False)
    np.testing.assert_array_equal(r1.actions, r2.actions)
    assert r1.length == 48 and json.dumps([o.to_json() for o in r1.outcomes])
