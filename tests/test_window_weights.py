"""data.window_weights: training windows in which an object moves or the gripper acts drawn so that they make up a
chosen share of what the model sees -- deterministic and resumable like the uniform order, which the default keeps
bit for bit."""
import dataclasses
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.core.config import Config, DataConfig, ModelConfig, TrainConfig, WindowWeights, config_from_dict
from sc3_jax.core.errors import UserError
from sc3_jax.data import norm_stats
from sc3_jax.data import pipeline as P
from sc3_jax.data import window_weights as W
from sc3_jax.data.episodes import Episode, EpisodeStore

K, T = 2, 3  # context and future frames: a window holds 5 frames at stride 1
LENGTH = 20
# per episode: (frames where the block moves to a new place, frames where the gripper toggles)
MOTION = {"e0": ((6,), ()), "e1": ((), (15,)), "e2": ((), ()), "e3": ((3, 12), (12,))}


def _one_line(err) -> str:
    msg = str(err.value)
    assert msg and "\n" not in msg, msg
    return msg


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Episodes whose block jumps by 5 cm at known frames (and wobbles by 1 mm every frame: below any threshold
    used) and whose gripper toggles at known frames; a joint moves every frame by 0.02 (below state_change)."""
    root = tmp_path_factory.mktemp("weights")
    s = EpisodeStore(root, views=["cam"], fps=10, image_size=(4, 4), create=True, action_dim=7, has_pose=True,
                     state_dim=2, state_names=["joint", "gripper"], object_state_dim=3,
                     object_state_names=["block_x", "block_y", "block_z"])
    rng = np.random.default_rng(0)
    for eid, (moves, toggles) in MOTION.items():
        t = np.arange(LENGTH)
        objects = np.zeros((LENGTH, 3)) + rng.uniform(-1e-3, 1e-3, (LENGTH, 3))
        for m in moves:
            objects[m:, 1] += 0.05
        gripper = np.zeros(LENGTH)
        for g in toggles:
            gripper[g:] = 1 - gripper[g:]
        state = np.stack([0.02 * t, gripper], -1)
        frames = rng.integers(0, 255, (LENGTH, 4, 4, 3), dtype=np.uint8)
        s.write(Episode(eid, {"cam": frames}, rng.normal(0, 0.01, (LENGTH, 7)).astype(np.float32),
                        rng.normal(0, 0.1, (LENGTH, 7)).astype(np.float32), state=state.astype(np.float32),
                        object_state=objects.astype(np.float32)))
    return s


def _cfg(store, **weights) -> DataConfig:
    return DataConfig(path=str(store.root), views=("cam",), image_size=(4, 4), context_frames=K, future_frames=T,
                      strides=(1,), pseudo_action_prob=0.0, batch_size=4, seed=3,
                      window_weights=WindowWeights(**weights))


def _expected_events(store, cfg) -> np.ndarray:
    """By hand: a window [start, start + K + T) has an event when a block jump (frame m: m-1 -> m) or a gripper
    toggle (frame g) happens inside it, i.e. start < m <= start + K + T - 1."""
    index = P.build_index(store, cfg)
    w = cfg.window_weights
    out = []
    for n, start in index.pairs:
        moves, toggles = MOTION[index.episode_ids[n]]
        marks = (list(moves) if w.objects else []) + (list(toggles) if w.state else [])
        out.append(any(start < m <= start + K + T - 1 for m in marks))
    return np.array(out)


@pytest.mark.parametrize("weights", [dict(objects=("block_y",), object_motion=0.02),
                                     dict(state=("gripper",), state_change=0.5),
                                     dict(objects=("0", "1", "2"), object_motion=0.02, state=("1",),
                                          state_change=0.5)])
def test_the_windows_with_an_event_are_those_where_the_named_entries_move(store, weights):
    cfg = _cfg(store, **weights)
    index = P.build_index(store, cfg)
    events = W.window_events(store, index, cfg)
    np.testing.assert_array_equal(events, _expected_events(store, cfg))
    assert 0 < events.sum() < len(events)
    # a threshold above the jump, or the slow joint, marks none
    assert not W.window_events(store, index, _cfg(store, objects=("block_y",), object_motion=0.06)).any()
    assert not W.window_events(store, index, _cfg(store, state=("joint",), state_change=0.1)).any()
    assert W.window_events(store, index, _cfg(store, state=("joint",), state_change=0.05)).all()


@pytest.mark.parametrize("share", [0.2, 0.5, 0.8])
def test_the_weighted_index_gives_event_windows_the_share_asked_for(store, share, capsys):
    cfg = _cfg(store, objects=("block_y",), object_motion=0.02, state=("gripper",), state_change=0.5, share=share)
    index = P.build_index(store, cfg)
    events = _expected_events(store, cfg)
    pairs = W.weighted_pairs(store, index, cfg, say=True)
    is_event = {tuple(p) for p in index.pairs[events]}
    got = np.mean([tuple(p) in is_event for p in pairs])
    assert abs(got - share) <= 1.0 / len(pairs)
    assert {tuple(p) for p in pairs} == {tuple(p) for p in index.pairs}  # every window still drawn
    line = capsys.readouterr().out.strip()
    assert "\n" not in line and f"({100 * events.mean():.1f}%) have an event" in line
    assert f"they are {100 * got:.1f}% of the {len(pairs)} drawn" in line


@settings(max_examples=200, deadline=None)
@given(st.lists(st.booleans(), min_size=2, max_size=400), st.floats(0.01, 0.95))
def test_multiplicities_give_any_reachable_share_with_whole_copies(events, share):
    events = np.array(events)
    if events.all() or not events.any():
        with pytest.raises(UserError):
            W.multiplicities(events, share)
        return
    mult = W.multiplicities(events, share)
    assert mult.dtype == np.int64 and mult.min() >= 1
    got = mult[events].sum() / mult.sum()
    natural = events.mean()
    assert abs(got - share) <= 1.0 / mult.sum() + 1e-12  # whole copies: within one copy of the share asked for
    group = events if share > natural else ~events  # only one group is repeated, each by base or base + 1
    assert (mult[~group] == 1).all() and mult[group].max() - mult[group].min() <= 1
    np.testing.assert_array_equal(W.multiplicities(events, share), mult)  # deterministic
    assert (W.multiplicities(events, 0.0) == 1).all()


def _batches(cfg, store, n: int, state=None):
    stats = norm_stats.NormStats.from_store(store)
    it = P.make_iterator(cfg, store, stats)
    if state is not None:
        it.set_state(state)
    return it, [next(it) for _ in range(n)]


def test_the_default_leaves_the_window_order_unchanged(store, capsys):
    """No weights: the pipeline shuffles build_index's pairs themselves (the order of every run before weights); a
    share of 0 with entries named says the share of event windows and draws the same order."""
    cfg = dataclasses.replace(_cfg(store), window_weights=WindowWeights())
    index = P.build_index(store, cfg)
    assert W.weighted_pairs(store, index, cfg) is index.pairs
    import grain

    order = grain.MapDataset.source(index.pairs).shuffle(seed=cfg.seed)
    want = [tuple(order[i]) for i in range(3 * cfg.batch_size)]
    _, batches = _batches(cfg, store, 3)
    got = [(int(e), int(s)) for b in batches for e, s in zip(b["episode"], b["start"])]
    assert got == want
    assert capsys.readouterr().out == ""  # nothing said
    measured = _cfg(store, objects=("block_y",), object_motion=0.02, share=0.0)
    _, same = _batches(measured, store, 3)
    for a, b in zip(batches, same):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    assert "drawn uniformly" in capsys.readouterr().out


def test_weighted_windows_resume_exactly_from_the_iterator_state(store):
    cfg = _cfg(store, objects=("block_y",), object_motion=0.02, state=("gripper",), state_change=0.5, share=0.7)
    it, first = _batches(cfg, store, 4)
    state = it.get_state()
    rest = [next(it) for _ in range(3)]
    _, again = _batches(cfg, store, 3, state=state)
    for a, b in zip(rest, again):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    # over whole epochs the event windows are drawn at the share asked for
    index = P.build_index(store, cfg)
    epoch = len(W.weighted_pairs(store, index, cfg))
    events = {tuple(p) for p in index.pairs[_expected_events(store, cfg)]}
    _, many = _batches(cfg, store, 2 * epoch // cfg.batch_size)
    drawn = [(int(e), int(s)) in events for b in many for e, s in zip(b["episode"], b["start"])]
    assert abs(np.mean(drawn) - 0.7) < 0.02


def test_weights_naming_entries_the_store_lacks_are_refused_in_one_line(store, tmp_path):
    from sc3_jax.data import synthetic
    from sc3_jax.data.shape import shape_from_dataset

    with pytest.raises(UserError) as e:
        W.check(_cfg(store, objects=("cup_x",), share=0.5), store)
    assert "cup_x" in _one_line(e) and "block_x" in _one_line(e)
    with pytest.raises(UserError) as e:
        W.check(_cfg(store, state=("7",), share=0.5), store)  # an index past the state's 2 entries
    assert "'7'" in _one_line(e)
    plain = synthetic.generate(tmp_path / "plain", 1, length=8, image_size=(8, 8), progress=False)
    cfg = Config(data=DataConfig(path=str(plain.root), image_size=(8, 8),
                                 window_weights=WindowWeights(objects=("block_x",), share=0.5)))
    with pytest.raises(UserError) as e:  # `sc3 train` refuses it before anything is read or cached
        shape_from_dataset(cfg, plain)
    assert "records no object_state" in _one_line(e)
    with pytest.raises(UserError) as e:  # no window has an event: no weights give it the share
        W.weighted_pairs(store, P.build_index(store, _cfg(store)),
                         _cfg(store, objects=("block_y",), object_motion=1.0, share=0.5))
    assert "none of the" in _one_line(e)
    with pytest.raises(ValueError):
        WindowWeights(share=0.5)  # a share of nothing
    with pytest.raises(ValueError):
        WindowWeights(objects=("a",), share=1.0)


def test_the_weights_are_recorded_in_config_json_and_old_ones_read_as_off():
    cfg = Config(data=DataConfig(window_weights=WindowWeights(share=0.5, objects=("block_x", "block_z"),
                                                              state=("gripper",), state_change=0.5)))
    back = config_from_dict(json.loads(json.dumps(dataclasses.asdict(cfg))))
    assert back == cfg and back.data.window_weights.objects == ("block_x", "block_z")
    old = dataclasses.asdict(Config())
    del old["data"]["window_weights"]  # a config.json from before
    assert config_from_dict(old).data.window_weights == WindowWeights()


def test_a_store_without_object_state_trains_two_steps_as_before(tmp_path):
    """The synthetic store has no object state (as every store before it): the tiny model trains on it, and its
    config.json records the weights off."""
    from sc3_jax.data import synthetic
    from sc3_jax.train import train

    data = synthetic.generate(tmp_path / "episodes", 3, length=12, image_size=(8, 8), seed=0, progress=False)
    assert data.object_state_dim is None
    cfg = Config(model=ModelConfig(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                   rope_axes_dim=(2, 3, 3)),
                 data=DataConfig(path=str(data.root), image_size=(8, 8), context_frames=1, future_frames=2,
                                 batch_size=8),
                 train=TrainConfig(workdir=str(tmp_path / "run"), steps=2, ckpt_every=2, log_every=1, lr=1e-3,
                                   warmup_steps=1, progress=False, tensorboard=False, async_checkpointing=False))
    last = train.train(cfg)
    assert np.isfinite(last["loss"])
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["data"]["window_weights"]["share"] == 0
    assert config_from_dict(saved).data.window_weights == WindowWeights()


def test_a_store_with_object_states_reads_its_windows_from_cached_latents_too(store):
    """Windows whose frames come from the latent cache read each episode's trajectory arrays: the object state is
    not among those a window needs (it was a TypeError there)."""
    class Latents:  # latent_cache.LatentReader's one method the pipeline calls
        def window(self, ep_num, idx):
            return np.full((1, len(idx), 1, 1, 1), ep_num, np.float16)

    cfg = _cfg(store, objects=("block_y",), object_motion=0.02, share=0.5)
    ds = P.make_dataset(cfg, store, norm_stats.NormStats.from_store(store), latents=Latents())
    batch = ds[0]
    assert batch["latents"].shape[:3] == (cfg.batch_size, 1, K + T) and "frames" not in batch
    np.testing.assert_array_equal(batch["latents"][:, 0, 0, 0, 0, 0], batch["episode"])
