"""The SO-101 simulator as a gymnasium vector env (``sc3_jax/benchmarks/so101/vec_env.py``, what ``lerobot-eval
--env.type=sc3_so101`` runs): gymnasium's own env checker, seed s is the sweep's condition s, an episode ends and
succeeds as the benchmark's real episode does, SAME_STEP autoreset to the next unused condition. Needs the ``so101``
extra (no lerobot); tests/test_lerobot_so101.py runs it under the real lerobot-eval."""
import warnings

import numpy as np
import pytest

pytest.importorskip("lerobot_env_so101")

from sc3_jax.benchmarks.so101.controllers import ScriptedSo101  # noqa: E402
from sc3_jax.benchmarks.so101.env import VIEWS, So101Env  # noqa: E402
from sc3_jax.benchmarks.so101.rollouts import HOLD, run_episode  # noqa: E402
from sc3_jax.benchmarks.so101.sweep import EVAL_SEED0, HOLD_STEPS, write_conditions  # noqa: E402
from sc3_jax.benchmarks.so101.vec_env import So101GymEnv, vec_env  # noqa: E402
from sc3_jax.core.errors import UserError  # noqa: E402

SIZE = (24, 32)


def test_one_table_passes_gymnasiums_env_checker():
    from gymnasium.utils.env_checker import check_env

    env = So101GymEnv(image_size=SIZE, max_steps=5)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its advice on unbounded state boxes and on envs made without gym.make
            check_env(env)
        assert env.render().shape == (*SIZE[:1], 2 * SIZE[1], 3)  # the two views side by side
    finally:
        env.close()


def test_seed_s_is_the_sweeps_condition_s_and_its_observation_is_lerobots_raw_keys(tmp_path):
    env = vec_env(2, image_size=SIZE)
    try:
        obs, info = env.reset(seed=3)
        assert set(obs) == {"pixels", "agent_pos"} and set(obs["pixels"]) == set(VIEWS)
        assert obs in env.observation_space and env.action_space.shape == (2, 4)
        assert list(info["seed"]) == [3, 4]
        write_conditions(tmp_path, [EVAL_SEED0 + 3, EVAL_SEED0 + 4], SIZE, VIEWS)  # the sweep's initial conditions
        from sc3_jax.data.episodes import EpisodeStore

        store = EpisodeStore(tmp_path)
        for k, s in enumerate((3, 4)):
            ep = store.load(f"seed{EVAL_SEED0 + s}")  # the reset frame, then the frame after the HOLD step
            for v in VIEWS:
                assert np.array_equal(obs["pixels"][v][k], np.asarray(ep.frames[v])[HOLD_STEPS])
            assert np.array_equal(obs["agent_pos"][k], ep.state[HOLD_STEPS])
        again, _ = env.reset(seed=[4, 3])  # a list gives each env its seed
        assert np.array_equal(again["agent_pos"][0], obs["agent_pos"][1])
        assert np.array_equal(again["pixels"]["wrist"][1], obs["pixels"]["wrist"][0])
        assert env.call("_max_episode_steps") == (100, 100)  # the sweep's horizon, what lerobot-eval reads
        assert env.call("task_description")[0] == "pick the block and place it on the goal"
    finally:
        env.close()


def test_an_episode_succeeds_and_ends_as_the_benchmarks_real_one_then_the_env_resets_to_a_new_condition():
    """Env 0 runs the clean controller from condition 1, env 1 holds still: env 0's success and length are those of
    the benchmark's real episode (``run_episode`` from seed EVAL_SEED0 + 1 after the HOLD step), its final_info says
    so in the step it ends, and in that step it is reset to condition 1 + num_envs."""
    sim = So101Env(SIZE)
    try:
        real = run_episode(sim, ScriptedSo101(seed=0), EVAL_SEED0 + 1, max_steps=100, record=False, hold=HOLD_STEPS)
    finally:
        sim.close()
    assert real.succeeded and real.steps < 100
    env = vec_env(2, image_size=SIZE)
    try:
        env.reset(seed=1)
        table = env.envs[0].sim
        ctl = ScriptedSo101(seed=0)
        ctl.reset(EVAL_SEED0 + 1)
        for t in range(real.steps):
            state = {"environment_state": np.r_[table.block_pos(), table.goal_pos()]}
            obs, reward, terminated, truncated, info = env.step(np.stack([ctl(table, state), HOLD]))
            assert not truncated.any()
            if t < real.steps - 1:
                assert not terminated.any() and not info["is_success"].any()
        assert terminated.tolist() == [True, False] and reward.tolist() == [1.0, 0.0]
        final = info["final_info"]
        assert final["is_success"].tolist() == [True, False] and final["_is_success"].tolist() == [True, False]
        assert info["seed"].tolist() == [3, 2]  # env 0's next condition: its last + num_envs
        assert np.array_equal(obs["agent_pos"][0], env.envs[0].reset(seed=3)[0]["agent_pos"])
    finally:
        env.close()


def test_the_horizon_truncates_an_episode_that_did_not_succeed_and_errors_are_one_line():
    env = vec_env(1, image_size=SIZE, max_steps=3)
    try:
        env.reset(seed=0)
        for _ in range(3):
            _, _, terminated, truncated, info = env.step(HOLD[None])
        assert truncated.tolist() == [True] and not terminated.any()
        assert info["final_info"]["is_success"].tolist() == [False] and info["seed"].tolist() == [1]
        with pytest.raises(UserError, match="0 or more"):
            env.reset(seed=-1)
    finally:
        env.close()
    with pytest.raises(UserError, match="num_envs=0"):
        vec_env(0)
