"""The synthetic multi-view pushing world."""
import copy

import numpy as np
import pytest

from sc3_jax.data import synthetic as S
from sc3_jax.data.episodes import EpisodeStore


def _arrays(store):
    out = {}
    for eid in store.episode_ids():
        ep = store.load(eid, mmap=False)
        out[eid] = (ep.actions, ep.ee_pose, {v: np.asarray(f) for v, f in ep.frames.items()}, ep.prompt)
    return out


def _same(a, b):
    return (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
            and all(np.array_equal(a[2][v], b[2][v]) for v in a[2]) and a[3] == b[3])


def test_generate_is_deterministic_resumable_and_seed_dependent(tmp_path):
    a = S.generate(tmp_path / "a", 3, length=12, seed=5, progress=False)
    # resumable: a partial run followed by the rest gives the same episodes
    S.generate(tmp_path / "b", 1, length=12, seed=5, progress=False)
    b = S.generate(tmp_path / "b", 3, length=12, seed=5, progress=False)
    c = S.generate(tmp_path / "c", 3, length=12, seed=6, progress=False)
    ra, rb, rc = _arrays(a), _arrays(b), _arrays(c)
    assert list(ra) == ["ep000000", "ep000001", "ep000002"]
    assert all(_same(ra[k], rb[k]) for k in ra)
    assert not any(_same(ra[k], rc[k]) for k in ra)
    assert not _same(ra["ep000000"], ra["ep000001"])
    ep = a.load("ep000000")
    assert ep.frames["left"].shape == (12, 16, 16, 3) and ep.actions.shape == (12, 7)
    assert ep.prompt == S.PROMPT
    # an existing episode is not rewritten
    mtime = (tmp_path / "a" / "ep000000" / "actions.npy").stat().st_mtime_ns
    S.generate(tmp_path / "a", 3, length=12, seed=5, progress=False)
    assert (tmp_path / "a" / "ep000000" / "actions.npy").stat().st_mtime_ns == mtime
    with pytest.raises(ValueError):
        S.generate(tmp_path / "a", 3, length=12, image_size=(32, 32), seed=5, progress=False)


@pytest.mark.parametrize("size, episodes", [((16, 16), 6), ((32, 32), 2)])
def test_pixel_change_fraction_is_large(size, episodes):
    fracs = {v: [] for v in S.VIEWS}
    for i in range(episodes):
        ep = S.rollout(size, 60, np.random.SeedSequence([0, i]))
        assert ep.frames["left"].shape == (60, *size, 3)
        for v, f in S.view_change_fractions(ep).items():
            fracs[v].append(f)
    mean = {v: float(np.mean(f)) for v, f in fracs.items()}
    assert mean["left"] >= 0.15 and mean["right"] >= 0.15, mean
    assert mean["wrist"] >= 0.5, mean


def test_pixel_change_fraction_counts_pixels():
    f = np.zeros((3, 4, 4, 3), np.uint8)
    f[1, 0, :2, 1] = 100  # 2 of 16 pixels change from 0->1 and back 1->2
    f[2, 3, 3, 0] = 3  # below the threshold
    assert S.pixel_change_fraction(f, threshold=4) == pytest.approx(2 / 16)


def test_frames_depend_on_every_action_dimension():
    env = S.SyntheticEnv((16, 16), seed=3, num_objects=2)
    env.pos[:] = [0.0, 0.0, 0.08]
    env.width = 0.04
    base_action = np.array([0.01, -0.01, 0.005, 0.02, -0.02, 0.05, 0.04])
    ref = copy.deepcopy(env).step(base_action)
    deltas = [0.02, 0.02, 0.02, 0.1, 0.1, 0.2, 0.04]
    for k in range(7):
        a = base_action.copy()
        a[k] += deltas[k]
        out = copy.deepcopy(env).step(a)
        changed = {v: int(np.sum(np.any(out[v] != ref[v], axis=-1))) for v in S.VIEWS}
        assert all(n >= 5 for n in changed.values()), (k, changed)  # every view sees every action dimension


def test_pose_and_actions_are_consistent():
    ep = S.rollout((16, 16), 50, seed=11)
    pose, act = ep.ee_pose.astype(np.float64), ep.actions.astype(np.float64)
    assert np.all(np.isfinite(pose)) and np.all(np.isfinite(act))
    lo, hi = S.Z_RANGE
    assert np.all((pose[:, 2] >= lo - 1e-6) & (pose[:, 2] <= hi + 1e-6))
    assert np.all((pose[:, 6] >= -1e-6) & (pose[:, 6] <= S.GRIPPER_MAX + 1e-6))
    assert np.all(np.abs(np.diff(pose[:, 6])) <= S.GRIPPER_RATE + 1e-6)  # gripper rate limit
    inside = np.all(np.abs(pose[1:, :2]) < S.XY_LIMIT - 1e-4, axis=1) & (pose[1:, 2] > lo + 1e-4) & (pose[1:, 2] < hi - 1e-4)
    dxyz = np.diff(pose[:, :3], axis=0)
    np.testing.assert_allclose(dxyz[inside], act[:-1][inside, :3], atol=1e-6)
    assert act[:, :3].std() > 1e-3 and act[:, 3:6].std() > 1e-2  # not static


def test_blocks_get_pushed():
    moved = 0
    for i in range(4):
        env = S.SyntheticEnv((16, 16), seed=np.random.SeedSequence([0, i]))
        start = env.blocks.copy()
        policy = S.RandomExplorer(np.random.default_rng(i))
        for _ in range(80):
            env.step(policy(env))
        moved += int(np.any(np.abs(env.blocks - start) > 1e-3))
    assert moved >= 2


def test_store_round_trip(tmp_path):
    store = S.generate(tmp_path, 1, length=10, image_size=(32, 32), seed=0, progress=False)
    again = EpisodeStore(tmp_path)
    assert again.views == list(S.VIEWS) and again.image_size == (32, 32) and again.fps == S.FPS
    assert store.load("ep000000").frames["wrist"].shape == (10, 32, 32, 3)
