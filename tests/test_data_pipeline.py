"""The training-data pipeline: windows, strides, pseudo-actions, normalisation, sharding, resume, bad input."""
import dataclasses
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from sc3_jax.core.config import DataConfig
from sc3_jax.data import norm_stats
from sc3_jax.data import pipeline as P
from sc3_jax.data import rotations as R
from sc3_jax.data import synthetic as S
from sc3_jax.data.action_space import DELTA_EE
from sc3_jax.data.episodes import Episode, EpisodeError, EpisodeStore

LENGTH = 30


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("episodes")
    return S.generate(root, num_episodes=5, length=LENGTH, image_size=(16, 16), seed=1, progress=False)


def _cfg(store, **kw):
    base = dict(path=str(store.root), batch_size=8, context_frames=2, future_frames=4, seed=3)
    base.update(kw)
    return DataConfig(**base)


@pytest.fixture(scope="module")
def stats(store):
    return norm_stats.NormStats.from_store(store)


# -- rotations --------------------------------------------------------------------------------------------------
def test_rotvec_round_trip_including_near_zero_and_pi():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 1e-3, 150), [0, 1e-12, 1e-8, 1e-5, 1e-3],
                             np.full(45, np.pi - 1e-7)])
    r = axes * angles[:, None]
    m = R.rotvec_to_matrix(r)
    np.testing.assert_allclose(m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)
    back = R.matrix_to_rotvec(m)
    np.testing.assert_allclose(back, r, atol=1e-6)
    # exactly pi: r and -r are the same rotation
    rp = axes[:5] * np.pi
    mp = R.matrix_to_rotvec(R.rotvec_to_matrix(rp))
    np.testing.assert_allclose(R.rotvec_to_matrix(mp), R.rotvec_to_matrix(rp), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(mp, axis=-1), np.pi, atol=1e-9)


def test_rotations_match_scipy():
    Rot = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    np.testing.assert_allclose(R.rotvec_to_matrix(a), Rot.from_rotvec(a).as_matrix(), atol=1e-12)
    want = (Rot.from_rotvec(a) * Rot.from_rotvec(b)).as_rotvec()
    np.testing.assert_allclose(R.compose_rotvec(a, b), want, atol=1e-9)
    np.testing.assert_allclose(R.relative_rotvec(a, b), (Rot.from_rotvec(b) * Rot.from_rotvec(a).inv()).as_rotvec(),
                               atol=1e-9)


# -- normalisation ----------------------------------------------------------------------------------------------
def test_norm_stats_round_trip(store, stats, tmp_path):
    all_actions = np.concatenate([store.load(e).actions for e in store.episode_ids()])
    np.testing.assert_allclose(stats.mean, all_actions.mean(0), atol=1e-6)
    np.testing.assert_allclose(stats.std, np.maximum(all_actions.std(0), norm_stats.STD_FLOOR), rtol=1e-4)
    z = stats.normalize(all_actions)
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-3)
    np.testing.assert_allclose(z.std(0), 1, atol=1e-3)
    np.testing.assert_allclose(stats.denormalize(z), all_actions, atol=1e-6)
    stats.save(tmp_path / "norm.json")
    loaded = norm_stats.NormStats.load(tmp_path / "norm.json")
    np.testing.assert_array_equal(loaded.mean, stats.mean)
    np.testing.assert_array_equal(loaded.std, stats.std)
    # the floor on a constant dimension
    const = norm_stats.NormStats.from_actions(np.ones((10, 7)))
    assert np.all(const.std == np.float32(norm_stats.STD_FLOOR))


# -- windows ----------------------------------------------------------------------------------------------------
def test_batch_format_and_window_frames(store, stats):
    cfg = _cfg(store)
    ds = P.make_dataset(cfg, store, stats)
    seen_strides, seen_pseudo = set(), set()
    ids = store.episode_ids()
    for i in range(4):
        b = ds[i]
        assert b["frames"].shape == (8, 3, 6, 16, 16, 3) and b["frames"].dtype == np.uint8
        assert b["actions"].shape == (8, 4, 7) and b["actions"].dtype == np.float32
        assert b["stride"].dtype == np.int32 and b["pseudo"].dtype == np.bool_
        for k in range(8):
            ep = store.load(ids[b["episode"][k]], mmap=False)
            s, t0 = int(b["stride"][k]), int(b["start"][k])
            idx = t0 + s * np.arange(6)
            for v, view in enumerate(cfg.views):
                np.testing.assert_array_equal(b["frames"][k, v], ep.frames[view][idx])
            want = P.window_actions(ep.actions, ep.ee_pose, t0, s, 2, 4, bool(b["pseudo"][k]), DELTA_EE)
            np.testing.assert_allclose(stats.denormalize(b["actions"][k]), want, atol=1e-6)
            if not b["pseudo"][k] and s == 1:
                np.testing.assert_allclose(stats.denormalize(b["actions"][k]), ep.actions[idx[1:5]], atol=1e-6)
            seen_strides.add(s)
            seen_pseudo.add(bool(b["pseudo"][k]))
    assert seen_strides == {1, 2} and seen_pseudo == {True, False}


def test_stride2_composed_actions_match_the_poses(store, stats):
    """In the synthetic env R_{t+1} = R(a_t) R_t exactly, so composing two recorded rotations must reproduce the
    pose change over two frames; xyz is the sum of the deltas; the gripper is the last target."""
    cfg = _cfg(store, strides=(2,), pseudo_action_prob=0.0)
    b = P.make_dataset(cfg, store, stats)[0]
    assert np.all(b["stride"] == 2) and not np.any(b["pseudo"])
    ids = store.episode_ids()
    for k in range(8):
        ep = store.load(ids[b["episode"][k]], mmap=False)
        acts = stats.denormalize(b["actions"][k])
        for j in range(4):
            t = int(b["start"][k]) + 2 * (1 + j)
            np.testing.assert_allclose(acts[j, :3], ep.actions[t, :3] + ep.actions[t + 1, :3], atol=1e-6)
            want_rot = R.relative_rotvec(ep.ee_pose[t, 3:6], ep.ee_pose[t + 2, 3:6])
            np.testing.assert_allclose(acts[j, 3:6], want_rot, atol=2e-5)
            assert acts[j, 6] == pytest.approx(ep.actions[t + 1, 6], abs=1e-6)
            # and it is not simply the sum of the two rotation vectors in general
    single = P.compose_actions(np.array([[0, 0, 0, 1.0, 0, 0, 0], [0, 0, 0, 0, 1.0, 0, 0.5]]), 0, 2, DELTA_EE)
    assert not np.allclose(single[3:6], [1.0, 1.0, 0.0], atol=1e-2)
    np.testing.assert_allclose(single[3:6], R.compose_rotvec([0, 1.0, 0], [1.0, 0, 0]), atol=1e-6)


def test_pseudo_actions_of_pure_translation(tmp_path):
    T = 20
    v = np.array([0.01, -0.02, 0.005])
    pose = np.zeros((T, 7), np.float32)
    pose[:, :3] = np.arange(T)[:, None] * v
    pose[:, 3:6] = [0.3, -0.2, 1.0]  # constant (non-trivial) orientation
    pose[:, 6] = 0.04
    actions = np.tile(np.array([*v, 0, 0, 0, 0.04], np.float32), (T, 1))
    frames = {view: np.zeros((T, 16, 16, 3), np.uint8) for view in S.VIEWS}
    st = EpisodeStore(tmp_path, views=list(S.VIEWS), fps=20, image_size=(16, 16), create=True)
    st.write(Episode("trans", frames, actions, pose, "move"))
    stats = norm_stats.NormStats(np.zeros(7), np.ones(7))
    for stride in (1, 2):
        cfg = DataConfig(path=str(tmp_path), batch_size=4, strides=(stride,), pseudo_action_prob=1.0)
        b = P.make_dataset(cfg, st, stats)[0]
        assert np.all(b["pseudo"])
        want = np.array([*(stride * v), 0, 0, 0, 0.04], np.float32)
        np.testing.assert_allclose(b["actions"], np.broadcast_to(want, b["actions"].shape), atol=1e-6)


def test_pseudo_actions_approximate_recorded_on_synthetic(store):
    ep = store.load(store.episode_ids()[0])
    idx = np.arange(ep.length)
    pa = P.pseudo_actions(ep.ee_pose, idx)
    rec = ep.actions[:-1]
    np.testing.assert_allclose(pa[:, 3:6], rec[:, 3:6], atol=2e-5)  # rotations exact
    assert np.median(np.abs(pa[:, :3] - rec[:, :3])) < 1e-6  # xyz equal except at walls


# -- determinism, sharding, resume ------------------------------------------------------------------------------
def _equal(a, b):
    return set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)


def test_deterministic_and_seed_dependent(store, stats):
    cfg = _cfg(store)
    a, b = P.make_dataset(cfg, store, stats), P.make_dataset(cfg, store, stats)
    assert all(_equal(a[i], b[i]) for i in range(3))
    c = P.make_dataset(dataclasses.replace(cfg, seed=4), store, stats)
    assert not _equal(a[0], c[0])


@pytest.mark.parametrize("count", [2, 4])
def test_process_shards_concatenate_to_global_batch(store, stats, count):
    cfg = _cfg(store)
    glob = P.make_dataset(cfg, store, stats)
    shards = [P.make_dataset(cfg, store, stats, process_index=p, process_count=count) for p in range(count)]
    for i in (0, 1, 7):
        parts = [s[i] for s in shards]
        assert parts[0]["frames"].shape[0] == 8 // count
        cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        assert _equal(cat, glob[i])
    with pytest.raises(ValueError):
        P.make_dataset(cfg, store, stats, process_index=0, process_count=3)


@pytest.mark.parametrize("threads", [0, 2])
def test_iterator_exact_resume(store, stats, threads):
    cfg = _cfg(store, read_threads=threads)
    it = P.make_iterator(cfg, store, stats)
    first = [next(it) for _ in range(5)]
    state = it.get_state()
    json.dumps(state)  # the trainer stores it as JSON
    after = [next(it) for _ in range(3)]
    fresh = P.make_iterator(cfg, store, stats)
    fresh.set_state(state)
    again = [next(fresh) for _ in range(3)]
    assert all(_equal(x, y) for x, y in zip(after, again))
    ds = P.make_dataset(cfg, store, stats)  # iterator order = random-access order
    assert all(_equal(first[i], ds[i]) for i in range(5)) and _equal(after[0], ds[5])


def test_epochs_cover_every_window_once(store, stats):
    cfg = _cfg(store, batch_size=1, strides=(1,))
    index = P.build_index(store, cfg)
    n = len(index)
    assert n == 5 * (LENGTH - P.window_span(1, 2, 4) + 1)
    ds = P.make_dataset(cfg, store, stats, index=index)
    epoch0 = {(int(ds[i]["episode"][0]), int(ds[i]["start"][0])) for i in range(n)}
    assert epoch0 == {tuple(p) for p in index.pairs.tolist()}
    order0 = [int(ds[i]["start"][0]) for i in range(n)]
    order1 = [int(ds[n + i]["start"][0]) for i in range(n)]
    assert order0 != order1  # reshuffled each epoch


# -- bad input --------------------------------------------------------------------------------------------------
def _hash_dir(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        h.update(str(p.relative_to(root)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def _corrupt_missing_view(d):
    os.remove(d / "frames" / "wrist.npy")


def _corrupt_action_dim(d):
    np.save(d / "actions.npy", np.zeros((LENGTH, 6), np.float32))


def _corrupt_nan_actions(d):
    a = np.load(d / "actions.npy")
    a[7, 2] = np.nan
    np.save(d / "actions.npy", a)


def _corrupt_inf_pose(d):
    p = np.load(d / "ee_pose.npy")
    p[3, 4] = np.inf
    np.save(d / "ee_pose.npy", p)


def _corrupt_short(d):
    for f in ("actions.npy", "ee_pose.npy", *[f"frames/{v}.npy" for v in S.VIEWS]):
        np.save(d / f, np.load(d / f)[:9])  # 9 < (2 + 4 - 1) * 2 + 1 = 11 frames for one stride-2 window
    meta = json.loads((d / "meta.json").read_text())
    (d / "meta.json").write_text(json.dumps({**meta, "length": 9}))


@pytest.mark.parametrize("corrupt, field", [
    (_corrupt_missing_view, "frames/wrist"),
    (_corrupt_action_dim, "actions"),
    (_corrupt_nan_actions, "actions"),
    (_corrupt_inf_pose, "ee_pose"),
    (_corrupt_short, "length"),
])
def test_bad_episode_raises_and_leaves_files_untouched(store, stats, tmp_path, corrupt, field):
    root = tmp_path / "bad"
    shutil.copytree(store.root, root)
    bad = store.episode_ids()[2]
    corrupt(root / bad)
    before = _hash_dir(root)
    st = EpisodeStore(root)
    cfg = _cfg(st)
    with pytest.raises(EpisodeError) as e:
        P.make_dataset(cfg, st, stats)
    assert e.value.episode == bad and e.value.field == field
    with pytest.raises(EpisodeError) as e:
        P.build_index(st, cfg)
    assert e.value.episode == bad and e.value.field == field
    if field != "length":  # statistics need every episode readable, but not long enough for a window
        with pytest.raises(EpisodeError) as e:
            norm_stats.NormStats.from_store(st)
        assert e.value.episode == bad and e.value.field == field
    assert _hash_dir(root) == before
    assert sorted(p.name for p in root.iterdir()) == sorted(p.name for p in store.root.iterdir())


def test_short_episode_is_fine_for_stride_one_only(store, stats, tmp_path):
    root = tmp_path / "short"
    shutil.copytree(store.root, root)
    _corrupt_short(root / store.episode_ids()[0])
    st = EpisodeStore(root)
    index = P.build_index(st, _cfg(st, strides=(1,)))  # 9 frames hold 4 stride-1 windows of 6
    assert int(np.sum(index.pairs[:, 0] == 0)) == 9 - 6 + 1
