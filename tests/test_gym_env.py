"""The world model as a gymnasium vector env (sc3_jax/evaluation/gym_env.py) on test_any_robot.py's tiny bimanual
model: a policy driven through the env's step loop, one action per step as LeRobot's select_action pops its queue,
imagines exactly what `sc3 sweep episodes` imagines for the same conditions, seeds and policy (frames, states, U,
outcomes); its spaces and seeding pass gymnasium's env_checker-style checks; chunking and refusals as documented."""
import math

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from sc3_jax.cli import main  # noqa: E402
from sc3_jax.core.errors import UserError  # noqa: E402
from test_any_robot import A, CAMS, bimanual  # noqa: E402, F401  (the fixture: imported store + trained tiny model)
from test_ic_sweep import _conditions  # noqa: E402

CHUNK = 8  # the fixture model's rollout.policy_chunk
OFFSETS = {"hold": 0.0, "reach": 0.3}


class Offset:
    """Absolute joint targets a fixed offset from the state observed at each chunk (a HostPolicy for the sweep)."""
    chunk, action_dim = CHUNK, A

    def __init__(self, d):
        self.d = d

    def infer(self, obs):
        return np.repeat(np.asarray(obs["state"])[None, :A] + self.d, CHUNK, 0).astype(np.float32)


def hold():
    return Offset(OFFSETS["hold"])


def reach():
    return Offset(OFFSETS["reach"])


def score(view):
    moved = float(np.mean(view.state[-1] - view.state[0]))
    return {"success": moved > 0.2, "moved": bool(moved > 0.05)}


class Queue:
    """LeRobot's chunking select_action: one action per call, a new inference when the queue is empty."""

    def __init__(self, policy, steps):
        self.policy, self.steps, self.queue = policy, steps, []

    def select(self, obs_i):
        if not self.queue:
            obs = {"images": np.stack([obs_i[f"observation.images.{c}"] for c in CAMS]),
                   "state": obs_i["observation.state"], "task": np.int32(0)}
            self.queue = list(self.policy.infer(obs)[:self.steps])
        return self.queue.pop(0)


@pytest.fixture(scope="module")
def setup(bimanual, tmp_path_factory):  # noqa: F811
    """(the trained run, 4 held-out conditions: the imported store's 2 episodes twice over)."""
    return bimanual[5].train.workdir, _conditions(bimanual[4], tmp_path_factory.mktemp("ic") / "heldout")


def _env(setup, n=2, **kw):
    from sc3_jax.evaluation.gym_env import WorldModelVecEnv

    run, ic = setup
    kw.setdefault("episode_seconds", 0.6)
    return WorldModelVecEnv(run, str(ic), n, scorer="test_gym_env:score", **kw)


def _episode(env, policy, seed):
    """One batch of episodes through step(), every env with ``policy``; -> (final_info, steps taken)."""
    obs, _ = env.reset(seed=seed)
    queues = [Queue(policy, env.action_steps) for _ in range(env.num_envs)]
    for t in range(env.max_episode_steps):
        acts = np.stack([q.select({k: v[i] for k, v in obs.items()}) for i, q in enumerate(queues)])
        obs, reward, term, trunc, info = env.step(acts)
        if (term | trunc).all():
            return info["final_info"], t + 1, reward
    raise AssertionError("no episode ended within _max_episode_steps")


def test_imagined_outcomes_through_the_env_equal_the_sweeps(setup, tmp_path):
    from sc3_jax.evaluation.results import ResultsStore

    run, ic = setup
    out = tmp_path / "sweep"
    assert main(["sweep", "episodes", "--data", str(ic), "--world-model", str(run), "--policies",
                 *[f"{p}=test_gym_env:{p}" for p in OFFSETS], "--scorer", "test_gym_env:score",
                 "--episodes", "2", "--calibration-episodes", "0", "--batch", "2", "--episode-seconds", "0.6",
                 "--taus", "inf", "--out", str(out), "--no-progress"]) == 0
    store = ResultsStore(out)
    recs = {r["id"]: r for r in store.records()}
    env = _env(setup)
    outcomes = {}
    for name, factory in (("hold", hold), ("reach", reach)):
        final, steps, reward = _episode(env, factory(), seed=0)
        assert steps == env.max_episode_steps and final["_is_success"].all()
        for i in range(2):
            rec = recs[f"{name}/{i}_online"]
            assert final["episode"][i] == rec["episode"]
            assert final["outcomes"][i] == rec["outcomes"]
            won = rec["outcomes"]["success"]
            assert final["is_success"][i] == won and reward[i] == float(won)
            outcomes[(name, i)] = rec["outcomes"]
    # the imagined arrays themselves: one more episode, read before the autoreset replaces them
    env2 = _env(setup)
    obs, _ = env2.reset(seed=0)
    queues = [Queue(reach(), env2.action_steps) for _ in range(2)]
    for _ in range(env2.max_episode_steps - 1):
        obs, *_ = env2.step(np.stack([q.select({k: v[i] for k, v in obs.items()}) for i, q in enumerate(queues)]))
    hist = [(np.concatenate(f, 1), np.concatenate(s, 0)) for f, s in env2._hist]
    for i in range(2):
        arrays = store.load_arrays(f"reach/{i}_online")
        frames, states = hist[i]
        kept = frames.shape[1]  # every chunk but the last: the env runs the last one on the final step
        np.testing.assert_array_equal(frames, arrays["frames"][:, :kept])
        np.testing.assert_allclose(states[1:], arrays["states"][:kept - 1], atol=1e-6)
    assert {o["success"] for o in outcomes.values()} == {True, False}, outcomes  # the two policies differ


def test_spaces_seeding_and_step_shapes_pass_env_checker_style_checks(setup):
    from gymnasium.utils.env_checker import data_equivalence

    env = _env(setup)
    so, sa = env.single_observation_space, env.single_action_space
    assert set(so.spaces) == {f"observation.images.{c}" for c in CAMS} | {"observation.state"}
    cam = so["observation.images.cam_high"]
    assert cam.shape == (24, 32, 3) and cam.dtype == np.uint8
    assert sa.shape == (A,) and env.action_space.shape == (2, A)
    assert env.observation_space["observation.state"].shape == (2, A)  # no learned state here: the imagined one
    obs1, info1 = env.reset(seed=1)
    assert env.observation_space.contains(obs1) and all(
        so.contains({k: v[i] for k, v in obs1.items()}) for i in range(2))
    obs2, info2 = env.reset(seed=1)
    assert data_equivalence(obs1, obs2) and list(info1["seed"]) == [1, 2]
    obs3, info3 = env.reset(seed=0)
    assert not data_equivalence(obs1, obs3)  # condition 0 in env 0, not condition 1
    np.testing.assert_array_equal(obs3["observation.images.cam_low"][1], obs1["observation.images.cam_low"][0])
    a = np.zeros((2, A), np.float32)
    for t in range(env.action_steps):
        obs, r, term, trunc, info = env.step(a)
        assert r.shape == term.shape == trunc.shape == (2,) and env.observation_space.contains(obs)
        if t < env.action_steps - 1:  # mid-chunk: the observation the chunk started from
            assert data_equivalence(obs, obs3) and info == {}
    assert not data_equivalence(obs, obs3) and info["u"].shape == (2,)  # the chunk's last kept frame
    assert env.call("_max_episode_steps") == (env.max_episode_steps,) * 2
    assert env.call("render")[0].shape == (24, 32 * len(CAMS), 3)
    assert env.call("task_description") == ("fold the towel",) * 2
    gym_keys = _env(setup, keys="gym")
    o, _ = gym_keys.reset(seed=0)
    assert set(o) == {"pixels", "agent_pos"} and set(o["pixels"]) == set(CAMS)
    np.testing.assert_array_equal(o["pixels"]["cam_high"], obs3["observation.images.cam_high"])


def test_action_steps_sets_the_chunk_and_refuses_what_the_model_cannot_predict(setup):
    env = _env(setup, action_steps=2)
    assert env.action_steps == 2 and env.spec.keep == 2 and env.max_episode_steps == env.spec.num_chunks * 2
    with pytest.raises(UserError, match="action_steps=99") as e:
        _env(setup, action_steps=99)
    assert "\n" not in str(e.value)


def test_misuse_is_one_line(setup):
    env = _env(setup, n=1)
    with pytest.raises(UserError, match="before reset"):
        env.step(np.zeros((1, A), np.float32))
    env.reset(seed=0)
    with pytest.raises(UserError, match=r"actions \[1, 7\]"):
        env.step(np.zeros((1, 7), np.float32))
    with pytest.raises(UserError, match="keys='pixels'"):
        _env(setup, keys="pixels")
    assert math.isinf(env.tau)
