"""Any robot: a bimanual robot's LeRobot dataset -- 14-D absolute joint actions, a 14-D joint
state, 4 cameras, non-square frames, no end-effector pose -- imports with its declared action space, trains the tiny
config with its shape read from dataset.json, and rolls out closed loop with a 14-D policy; every shape mismatch is
a one-line error naming both sides. Plus the action-space operations themselves (numpy and jnp twins)."""
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.rollout import imagination_state, rollout
from sc3_jax.core.config import load_config, replace
from sc3_jax.data import pipeline as P
from sc3_jax.data.action_space import DELTA_EE, ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.data.shape import check_shape, explicit_fields, shape_from_dataset
from sc3_jax.core.errors import UserError
from sc3_jax.policies.base import JaxPolicy

A = 14  # ALOHA: 2 x (6 joints + gripper)
CAMS = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
H, W = 24, 32
FPS = 20
LENGTH = 24


def _one_line(err) -> str:
    msg = str(err.value)
    assert "\n" not in msg and msg, msg
    return msg


# -- the action space's operations -------------------------------------------------------------------------------
def test_compose_integrate_and_hold_per_kind():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 4)).astype(np.float32)
    ab = ActionSpace("absolute", 4)
    np.testing.assert_array_equal(ab.compose(a), a[-1])  # the last target
    np.testing.assert_array_equal(ab.integrate(np.zeros(4), a), np.concatenate([np.zeros((1, 4)), a]))
    np.testing.assert_array_equal(ab.hold(a[-1], 2), np.stack([a[-1]] * 2))
    vel = ActionSpace("velocity", 4, targets=(3,))  # a gripper position among joint velocities
    c = vel.compose(a)
    np.testing.assert_allclose(c[:3], a[:, :3].mean(0), rtol=1e-6)
    assert c[3] == a[-1, 3]
    s = vel.integrate(np.ones(4), a, dt=0.1)
    np.testing.assert_allclose(s[1:, :3], 1 + 0.1 * np.cumsum(a[:, :3], 0), rtol=1e-6)
    np.testing.assert_array_equal(s[1:, 3], a[:, 3])
    np.testing.assert_array_equal(vel.hold(a[-1], 2), [[0, 0, 0, a[-1, 3]]] * 2)
    # composing at stride s then integrating at s * dt lands where integrating every step does (velocities)
    np.testing.assert_allclose(vel.integrate(np.ones(4), c[None], dt=0.3)[1, :3], s[-1, :3], rtol=1e-5)
    # delta_ee: exactly the benchmark's rules (pipeline.compose_actions is this)
    d = rng.normal(0, 0.1, size=(2, 7))
    np.testing.assert_array_equal(DELTA_EE.compose(d), P.compose_actions(d, 0, 2, DELTA_EE))
    assert DELTA_EE.hold(d[-1], 1)[0, 6] == np.float32(d[-1, 6]) and not DELTA_EE.hold(d[-1], 1)[0, :6].any()


@pytest.mark.parametrize("space", [DELTA_EE, ActionSpace("absolute", 5), ActionSpace("velocity", 5, targets=(4,))])
def test_jnp_twins_match_numpy(space):
    rng = np.random.default_rng(1)
    acts = rng.normal(0, 0.2, size=(6, space.dim)).astype(np.float32)
    s0 = rng.normal(0, 0.3, size=space.dim).astype(np.float32)
    got = np.asarray(imagination_state.frame_poses(jnp.asarray(s0), jnp.asarray(acts), space, 0.05))
    np.testing.assert_allclose(got, space.integrate(s0, acts, 0.05), atol=2e-6)
    comp = np.asarray(imagination_state.compose(jnp.asarray(acts), 3, space))
    np.testing.assert_allclose(comp, np.stack([space.compose(acts[i:i + 3]) for i in (0, 3)]), atol=2e-6)


def test_pseudo_actions_only_from_a_measured_pose():
    with pytest.raises(UserError) as e:
        ActionSpace("absolute", A).pseudo(np.zeros((5, 7)), np.arange(3))
    assert "absolute" in _one_line(e) and "pseudo_action_prob" in _one_line(e)
    with pytest.raises(UserError) as e:
        DELTA_EE.pseudo(None, np.arange(3))
    assert "ee_pose" in _one_line(e)
    assert DELTA_EE.pseudo_refusal(True) is None


def test_declarations_are_checked_in_one_line():
    for kwargs, word in ((dict(kind="joints"), "kind"), (dict(kind="delta_ee", dim=14), "7-D"),
                         (dict(kind="absolute", dim=3, names=("a", "b")), "names"),
                         (dict(kind="absolute", dim=3, targets=(1,)), "targets")):
        with pytest.raises(UserError) as e:
            ActionSpace(**kwargs)
        assert word in _one_line(e)


# -- stores: old ones read as before, new ones declare ---------------------------------------------------------
def _store(root, space, state_dim=None, n=2, length=LENGTH, views=CAMS, size=(H, W), has_pose=False, seed=0):
    rng = np.random.default_rng(seed)
    st = EpisodeStore(root, views=list(views), fps=FPS, image_size=size, create=True, action_space=space,
                      state_dim=state_dim, has_pose=has_pose)
    for i in range(n):
        q = np.cumsum(rng.normal(0, 0.05, size=(length + 1, space.dim)), 0).astype(np.float32)
        frames = {v: rng.integers(0, 256, (length, *size, 3), dtype=np.uint8) for v in views}
        acts = q[1:] if space.kind == "absolute" else (q[1:] - q[:-1]) * FPS
        st.write(Episode(f"ep{i}", frames, acts.astype(np.float32), None, "fold the towel", {},
                         q[:-1] if state_dim else None))
    return st


def test_a_store_without_declarations_reads_as_the_benchmark(tmp_path):
    from sc3_jax.data import synthetic

    st = synthetic.generate(tmp_path / "s", 1, length=10, image_size=(8, 8), progress=False)
    header = tmp_path / "s" / "dataset.json"
    info = json.loads(header.read_text())
    for k in ("action_space", "state", "ee_pose"):  # what a store written before declarations has
        info.pop(k)
    header.write_text(json.dumps(info))
    old = EpisodeStore(tmp_path / "s")
    assert old.action_space == DELTA_EE and old.has_pose and old.state_dim is None
    ep = old.load(st.episode_ids()[0])
    assert ep.ee_pose.shape == (10, 7) and ep.state is None
    assert NormStats.from_store(old).action_space == DELTA_EE


def test_store_refuses_arrays_it_does_not_declare(tmp_path):
    st = _store(tmp_path / "a", ActionSpace("absolute", A), state_dim=A, n=1)
    ep = st.load("ep0")
    from sc3_jax.data.episodes import EpisodeError
    with pytest.raises(EpisodeError, match="ee_pose"):  # a pose given to a store that has none: not dropped
        st.write(Episode("x", ep.frames, ep.actions, np.zeros((LENGTH, 7)), "", {}, ep.state))
    with pytest.raises(EpisodeError, match=r"state.*\[24, 14\]"):
        st.write(Episode("x", ep.frames, ep.actions, None, "", {}, ep.state[:, :7]))
    # velocities of what the robot does not record (end-effector deltas under a joint state) are a dataset too:
    # the commands integrate from zero and the policies read the learned state (state_head.py)
    v = EpisodeStore(tmp_path / "v", views=["a"], fps=FPS, image_size=(8, 8), create=True,
                     action_space=ActionSpace("velocity", A), state_dim=7)
    assert v.state_dim == 7 and v.action_space.dim == A
    np.testing.assert_array_equal(v.action_space.initial_state(np.ones((3, A)), None, np.ones((3, 7)), 2),
                                  np.zeros(A))


def test_norm_stats_and_windows_follow_the_space(tmp_path):
    st = _store(tmp_path / "v", ActionSpace("velocity", A), state_dim=A)
    stats = NormStats.from_store(st)
    assert stats.action_space.kind == "velocity" and stats.mean.shape == stats.pose_mean.shape == (A,)
    states = np.concatenate([st.load(e).state for e in st.episode_ids()])
    np.testing.assert_allclose(stats.pose_mean, states.mean(0), atol=1e-5)  # the recorded state's, not actions'
    stats.save(tmp_path / "n.json")
    assert NormStats.load(tmp_path / "n.json").action_space == stats.action_space
    cfg = replace(load_config("tiny"), data=dict(views=CAMS, image_size=(H, W), strides=(2,), batch_size=2,
                                                 pseudo_action_prob=0.0))
    b = P.make_dataset(cfg.data, st, stats)[0]
    assert b["actions"].shape == (2, 4, A) and b["pose"].shape == (2, 5, A)
    for k in range(2):  # mean velocities over the stride; the state integrated at stride / fps seconds
        ep = st.load(st.episode_ids()[int(b["episode"][k])])
        t = int(b["start"][k]) + 2  # frame K-1
        acts = b["actions"][k] * stats.std + stats.mean
        np.testing.assert_allclose(acts[0], ep.actions[t:t + 2].mean(0), atol=1e-5)
        pose = b["pose"][k] * stats.pose_std + stats.pose_mean
        np.testing.assert_allclose(pose[0], ep.state[t], atol=1e-5)
        np.testing.assert_allclose(pose[1:], ep.state[t + 2:t + 10:2], atol=1e-4)  # exact velocities: exact states
    with pytest.raises(UserError) as e:
        P.make_dataset(replace(cfg, data=dict(pseudo_action_prob=0.5)).data, st, stats)
    assert "pseudo_action_prob=0.5" in _one_line(e) and "velocity" in _one_line(e)


# -- the bimanual robot, end to end ------------------------------------------------------------------------------
def _lerobot(root):
    pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
    from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot

    rng = np.random.default_rng(0)
    eps = []
    for e in range(2):
        t, y, x = np.meshgrid(np.arange(LENGTH), np.arange(H), np.arange(W), indexing="ij")
        frames = {f"observation.images.{c}": np.stack([120 + 60 * np.sin(x / 5 + t / 4 + i + e),
                                                       120 + 60 * np.cos(y / 4 + t / 3 + i),
                                                       80 + 3 * t + 0 * x], -1).astype(np.uint8)
                  for i, c in enumerate(CAMS)}
        q = np.cumsum(rng.normal(0, 0.05, size=(LENGTH + 1, A)), 0).astype(np.float32)
        eps.append(RawEpisode(frames, q[1:], "fold the towel", q[:-1]))  # targets: the next joint positions
    names = [f"{side}_{j}" for side in ("left", "right") for j in ("waist", "shoulder", "elbow", "forearm_roll",
                                                                     "wrist_angle", "wrist_rotate", "gripper")]
    write_lerobot(root, eps, FPS, version="v3.0", names={"action": names, "observation.state": names},
                  robot_type="aloha")
    return eps, names


@pytest.fixture(scope="module")
def bimanual(tmp_path_factory):
    """The LeRobot dataset, imported with its declaration, and the tiny config trained 2 steps on it with no shape
    flags (small widths for a cheap test: widths are not shape flags)."""
    from sc3_jax.train import train
    from sc3_jax.data.lerobot_import import import_lerobot

    tmp = tmp_path_factory.mktemp("bimanual")
    raw, names = _lerobot(tmp / "lerobot")
    summary = import_lerobot(tmp / "lerobot", tmp / "store", action_space="absolute")
    store = EpisodeStore(tmp / "store")
    argv = ["--model.dim", "32", "--model.depth", "1", "--model.pose-conditioning", "True", "--train.steps", "2"]
    cfg = replace(load_config("tiny"),
                  model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, mlp_dim=64, pose_conditioning=True),
                  data=dict(path=str(tmp / "store"), batch_size=8),
                  train=dict(workdir=str(tmp / "run"), steps=2, log_every=1, ckpt_every=2, progress=False,
                             tensorboard=False, async_checkpointing=False),
                  rollout=dict(policy_chunk=8, keep_frames=3), sample=dict(steps=2))
    cfg = shape_from_dataset(cfg, store, explicit_fields(argv))
    last = train.train(cfg)
    return tmp, raw, names, summary, store, cfg, last


def test_import_takes_the_declaration(bimanual, tmp_path):
    from sc3_jax.data.lerobot_error import LeRobotError
    from sc3_jax.data.lerobot_import import import_lerobot

    tmp, raw, names, summary, store, cfg, _ = bimanual
    assert store.action_space == ActionSpace("absolute", A, tuple(names)) and store.state_dim == A
    assert not store.has_pose and store.views == list(CAMS) and tuple(store.image_size) == (H, W)
    assert summary["action_space"]["kind"] == "absolute" and summary["ee_pose"] is False
    ep = store.load(store.episode_ids()[1])
    np.testing.assert_array_equal(ep.actions, raw[1].action)
    np.testing.assert_array_equal(ep.state, raw[1].state)
    assert ep.ee_pose is None and store.state_names == tuple(names)
    with pytest.raises(LeRobotError) as e:  # 14-D actions and no declaration: say what to pass
        import_lerobot(tmp / "lerobot", tmp_path / "undeclared")
    assert "action_space" in _one_line(e) and "14-D" in _one_line(e)
    # our export writes the declaration into info.json, so a round trip needs none
    from sc3_jax.data.lerobot_write import export_store

    export_store(store, tmp_path / "lr", image_dtype="image")
    back = EpisodeStore(import_lerobot(tmp_path / "lr", tmp_path / "back")["out"])
    assert back.action_space == store.action_space and back.state_dim == A and not back.has_pose
    np.testing.assert_array_equal(back.load(store.episode_ids()[1]).state, ep.state)


def test_shape_comes_from_dataset_json(bimanual):
    _, _, _, _, store, cfg, last = bimanual
    assert cfg.data.views == CAMS and cfg.model.num_views == 4 and cfg.data.image_size == (H, W)
    assert cfg.model.action_dim == A and cfg.data.pseudo_action_prob == 0.0  # absolute targets: no pseudo-actions
    assert np.isfinite(last["loss"]) and last["step"] == 2
    check_shape(cfg, store)


@pytest.mark.parametrize("flags, field, words", [
    (dict(data=dict(views=("left", "right", "wrist"))), "data.views", ("['left', 'right', 'wrist']", "cam_high")),
    (dict(model=dict(num_views=3)), "model.num_views", ("model.num_views=3", "has 4")),
    (dict(data=dict(image_size=(16, 16))), "data.image_size", ("[16, 16]", "[24, 32]")),
    (dict(model=dict(action_dim=7)), "model.action_dim", ("model.action_dim=7", "14-D absolute")),
    (dict(data=dict(pseudo_action_prob=0.5)), "data.pseudo_action_prob", ("pseudo_action_prob=0.5", "absolute")),
])
def test_each_explicit_mismatch_is_one_line_naming_both_sides(bimanual, flags, field, words):
    store = bimanual[4]
    with pytest.raises(UserError) as e:
        shape_from_dataset(replace(load_config("tiny"), **flags), store, {field})
    msg = _one_line(e)
    assert all(w in msg for w in words) and "dataset.json" in msg, msg
    # not explicit: filled from the data instead
    assert shape_from_dataset(replace(load_config("tiny"), **flags), store).model.action_dim == A


def test_a_trained_model_against_another_store(bimanual, tmp_path):
    cfg = bimanual[5]
    other = _store(tmp_path / "o", ActionSpace("absolute", A), state_dim=A, n=1, size=(16, 16))
    with pytest.raises(UserError) as e:
        check_shape(cfg, other)
    assert "[24, 32]" in _one_line(e) and "[16, 16]" in _one_line(e)
    other = _store(tmp_path / "p", ActionSpace("absolute", 6), n=1, size=(H, W))
    with pytest.raises(UserError) as e:
        check_shape(cfg, other)
    assert "model.action_dim=14" in _one_line(e) and "6-D absolute" in _one_line(e)


def _follow(params, obs, rng):
    """A 14-D policy: small random steps from the state it observes (absolute targets)."""
    return obs["state"][None] + params[:, None] * jax.random.normal(rng, (params.shape[0], obs["state"].shape[0]))


def test_closed_loop_rollout_with_a_14d_policy(bimanual):
    from sc3_jax.model import checkpoint

    tmp, _, _, _, store, _, _ = bimanual
    cfg, stats, params = checkpoint.load(tmp / "run")
    assert stats.action_space.kind == "absolute" and stats.mean.shape == stats.pose_mean.shape == (A,)
    ro = rollout.Rollout(cfg, stats, data_fps=store.fps, num_chunks=2)
    items = [rollout.from_episode(store.load(e), cfg.data.views, ro.spec) for e in store.episode_ids()]
    ics = rollout.stack_initial_conditions([it[0] for it in items])
    ep = store.load(store.episode_ids()[0])
    np.testing.assert_array_equal(ics.state[0], ep.state[2])  # the measured joints at the last context frame
    policy = JaxPolicy("follow", _follow, jnp.full((8,), 0.01), chunk=8, action_dim=A)
    keys = rollout.episode_keys(0, 2)
    out = ro.run(params, policy, ics, keys, tau=math.inf)
    assert out["frames"].shape == (2, 4, 6, H, W, 3) and out["actions"].shape == out["states"].shape == (2, 6, A)
    np.testing.assert_array_equal(out["states"], out["actions"])  # absolute: the state is the last target
    host = ro.run_host(params, policy, ics, keys, tau=math.inf)
    np.testing.assert_allclose(host["actions"], out["actions"], atol=1e-5)
    # offline replay of the recorded targets; after the recording the robot holds its last target
    off = ro.run_offline(params, ics, np.stack([it[1] for it in items]), keys)
    np.testing.assert_array_equal(off["states"][0, :3], items[0][1][0, :3])


def test_policy_and_initial_state_mismatches_are_one_line(bimanual):
    from sc3_jax.model import checkpoint
    from sc3_jax.policies import simple

    tmp, _, _, _, store, _, _ = bimanual
    cfg, stats, params = checkpoint.load(tmp / "run")
    ro = rollout.Rollout(cfg, stats, data_fps=store.fps, num_chunks=1)
    ics = rollout.stack_initial_conditions([rollout.from_episode(store.load("lerobot000000"), cfg.data.views,
                                                                 ro.spec)[0]])
    keys = rollout.episode_keys(0, 1)
    with pytest.raises(UserError) as e:  # the benchmark's 7-D policy: refused before anything compiles
        ro.run(params, simple.zero_policy(8, action_space=DELTA_EE), ics, keys)
    assert "7-D" in _one_line(e) and "14-D" in _one_line(e)
    undeclared = JaxPolicy("seven", lambda p, o, r: jnp.zeros((8, 7)), None, chunk=8, action_dim=None)
    with pytest.raises(UserError) as e:  # declares nothing: its traced output shape says it
        ro.run(params, undeclared, ics, keys)
    assert "[8, 7]" in _one_line(e) and "[chunk, 14]" in _one_line(e)

    class Host:
        chunk = 8

        def infer(self, obs):
            return np.zeros((8, 7), np.float32)

    with pytest.raises(UserError) as e:  # a host policy is checked when its chunk arrives
        ro.run_host(params, Host(), ics, keys)
    assert "[8, 7]" in _one_line(e) and "14]" in _one_line(e)
    with pytest.raises(UserError) as e:
        ro.run(params, JaxPolicy("s", _follow, jnp.zeros(8), chunk=8, action_dim=A, state_dim=16), ics, keys)
    assert "16-D states" in _one_line(e) and "14-D states" in _one_line(e)
    with pytest.raises(UserError) as e:  # the benchmark's 7-D pose as initial state
        ro.run(params, JaxPolicy("f", _follow, jnp.zeros(8), chunk=8, action_dim=A),
               rollout.InitialConditions(ics.frames, np.zeros((1, 7), np.float32), ics.task), keys)
    assert "[1, 7]" in _one_line(e) and "[B, 14]" in _one_line(e)
    with pytest.raises(UserError) as e:  # norm stats of the benchmark under a 14-D model
        rollout.Rollout(cfg, NormStats(np.zeros(7), np.ones(7)), data_fps=store.fps)
    assert "7-D" in _one_line(e) and "model.action_dim is 14" in _one_line(e)


def test_velocity_rollout_integrates_at_the_policy_rate():
    """Velocities at policy_hz = 2 x control_hz: the model gets the mean of each pair, the imagined state moves
    by every raw velocity x 1 / policy_hz (a dt mix-up would scale it by 2)."""
    from sc3_jax.model import dit
    from sc3_jax.model.tokenizer import make_tokenizer

    space = ActionSpace("velocity", 4, targets=(3,))
    cfg = replace(load_config("tiny"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, mlp_dim=64,
                                                  action_dim=4, num_views=1, pose_conditioning=True),
                  data=dict(views=("cam",), image_size=(8, 8), context_frames=2, future_frames=4),
                  rollout=dict(policy_chunk=8, keep_frames=3, policy_hz=20.0), sample=dict(steps=1))
    tok = make_tokenizer(cfg.model)
    params = dit.init_params(cfg.model, tok.token_dim, jax.random.key(0), tok.grid((8, 8)))
    stats = NormStats(np.zeros(4), np.ones(4), action_space=space)
    ro = rollout.Rollout(cfg, stats, data_fps=20.0, num_chunks=1)
    assert (ro.spec.stride, ro.spec.ratio, ro.spec.raw_dt) == (2, 2, 0.05)
    raw = np.random.default_rng(0).normal(size=(8, 4)).astype(np.float32)
    policy = JaxPolicy("v", lambda p, o, r: p, jnp.asarray(raw), chunk=8, action_dim=4)
    s0 = np.array([[1.0, 2.0, 3.0, 0.5]], np.float32)
    ics = rollout.InitialConditions(np.zeros((1, 1, 2, 8, 8, 3), np.uint8), s0, np.zeros(1, np.int32))
    out = ro.run(params, policy, ics, rollout.episode_keys(0, 1), tau=math.inf)
    np.testing.assert_allclose(out["actions"][0], np.stack([space.compose(raw[i:i + 2]) for i in (0, 2, 4)]),
                               atol=1e-6)
    want = space.integrate(s0[0], raw[:6], dt=0.05)[2::2]  # the state at each kept frame (every 2nd raw action)
    np.testing.assert_allclose(out["states"][0], want, atol=1e-5)


# -- built-in policies and tau follow the world model's action space -----------------------------------------------
def test_tau_default_follows_the_action_space():
    """The core assumes no tau (its units are an action space's): None is no early termination for every action
    space, delta_ee included; the paper's 0.02 is the bussing benchmark's, set by its configs."""
    from sc3_jax.benchmarks.bussing.hooks import BENCHMARK_TAU

    assert BENCHMARK_TAU == 0.02  # the benchmark's, bit for bit
    assert rollout.resolve_tau(None) == math.inf
    assert rollout.resolve_tau(0.3) == 0.3  # a calibrated tau, as given
    assert rollout.resolve_tau(math.inf) == math.inf
    assert load_config("tiny").rollout.tau is None


def test_builtin_policy_rolls_out_a_14d_model_without_stopping_at_its_first_chunk(bimanual):
    """`zero` named for the 14-D model acts in [chunk, 14]; with the default tau the rollout runs its chunks, where
    the benchmark's 0.02 (raw radians here) would stop it at the first one."""
    from sc3_jax.model import checkpoint
    from sc3_jax.policies.resolve import resolve

    tmp, _, _, _, store, _, _ = bimanual
    cfg, stats, params = checkpoint.load(tmp / "run")
    assert cfg.rollout.tau is None  # the default, through config.json
    ro = rollout.Rollout(cfg, stats, data_fps=store.fps, num_chunks=2)
    assert ro.tau == math.inf
    policy = resolve("zero", cfg.rollout.policy_chunk, action_space=stats.action_space,
                     num_views=len(cfg.data.views)).policy
    assert policy.action_dim == A
    ics = rollout.stack_initial_conditions([rollout.from_episode(store.load(e), cfg.data.views, ro.spec)[0]
                                            for e in store.episode_ids()])
    keys = rollout.episode_keys(0, 2)
    out = ro.run(params, policy, ics, keys)
    assert out["actions"].shape == (2, 6, A) and out["tau"] == math.inf
    assert (out["terminated_at"] == -1).all() and out["frame_valid"].all()
    np.testing.assert_array_equal(out["actions"][:, :3], np.repeat(ics.state[:, None], 3, 1))  # stands still
    assert (out["u_raw"][:, 0] > 0.02).all()  # what the old default would have stopped at
    assert (ro.run(params, policy, ics, keys, tau=0.02)["terminated_at"] == 0).all()


def test_one_camera_turns_cross_view_inpainting_off_unless_it_was_asked_for(tmp_path):
    """A one-camera robot (an SO-101's): cross-view inpainting has no second view, so its share goes to forward and
    inverse dynamics in proportion; asked for explicitly, it is a one-line refusal."""
    store = _store(tmp_path / "one", DELTA_EE, views=("front",))
    cfg = load_config("tiny")
    fd, cvi, inv = cfg.modes.probs
    probs = shape_from_dataset(cfg, store).modes.probs
    assert probs[1] == 0 and probs[0] == pytest.approx(fd / (fd + inv)) and sum(probs) == pytest.approx(1)
    with pytest.raises(UserError) as e:
        shape_from_dataset(cfg, store, explicit_fields(["--modes.probs", "0.5", "0.2", "0.3"]))
    assert "cross-view inpainting" in _one_line(e) and "'front'" in _one_line(e)
    assert shape_from_dataset(replace(cfg, modes=dict(probs=(0.5, 0.0, 0.5))), store,
                              {"modes.probs"}).modes.probs == (0.5, 0.0, 0.5)
    four = _store(tmp_path / "four", DELTA_EE)
    assert shape_from_dataset(cfg, four).modes.probs == cfg.modes.probs  # two views or more: kept as asked


def test_diagnose_takes_the_model_s_own_action_space(bimanual):
    """`sc3 diagnose` of a 14-D absolute-action model runs (it once built its window from the simulated benchmark's
    7-D default action space and refused every other robot's model)."""
    from sc3_jax.evaluation import diagnose

    tmp, store = bimanual[0], bimanual[4]
    dc = diagnose.DiagnoseConfig(episodes=1, progress=False, batch=1)
    # a policy chunk of only the kept frames (3 of the 4 predicted), as SO-101's zoo plans
    short = replace(bimanual[5], rollout=dict(policy_chunk=3))
    result = diagnose.diagnose(str(tmp / "run"), store, dc, model_config=short)
    assert result["settings"]["sample_steps"] == 2 and result["gates"]
    assert result["teacher_forced"].get("available", True) and result["drift"].get("available", True)
    # absolute targets are shifted themselves: the counterfactual runs for this robot too (it once said "skipped")
    cf = result["counterfactual"]
    assert cf.get("readouts") or cf.get("notes")
    assert "counterfactual cosine" in diagnose.render_table(result)
