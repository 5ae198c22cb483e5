"""Closed-loop rollout engine (sc3_jax/rollout/rollout.py): scan vs host loop, U_chunk, termination, context caching,
offline replay, batching/sharding and the CLI. Tiny random-parameter models: semantics, not learning."""
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.rollout import imagination_state, rollout
from sc3_jax.core.config import config_from_dict, load_config, replace
from sc3_jax.data import rotations
from sc3_jax.data.action_space import DELTA_EE
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.evaluation import results
from sc3_jax.measures.metrics import psnr, psnr_by_view, termination_rate
from sc3_jax.model import dit
from sc3_jax.model.tokenizer import make_tokenizer, to_uint8
from sc3_jax.policies import simple
from sc3_jax.policies.base import as_host

B = 3  # episodes (padded to the 8 test devices)
N = 3  # chunks


def _cfg(**model):
    """Causal context attention (the paper config's): the rollouts below use the context cache unless told not to."""
    cfg = load_config("tiny")
    model = {"context_attention": "causal", **model}
    return replace(cfg, model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, mlp_dim=64, **model),
                   data=dict(image_size=(8, 8), context_frames=2, future_frames=4),
                   rollout=dict(policy_chunk=5, keep_frames=3), sample=dict(steps=2))


def _params(cfg, seed=0):
    tok = make_tokenizer(cfg.model)
    p = dit.init_params(cfg.model, tok.token_dim, jax.random.key(seed), tok.grid(cfg.data.image_size))
    # non-zero output weights so frames and re-read actions depend on everything
    return jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(seed + 1), x.shape), p)


STATS = NormStats(np.full(7, 0.001, np.float32), np.full(7, 0.01, np.float32), action_space=DELTA_EE)
FPS = 20.0  # the synthetic data's frame rate (what a saved model's checkpoint.read_robot gives)


def _ics(cfg, n=B, seed=0):
    rng = np.random.default_rng(seed)
    V, K, (H, W) = len(cfg.data.views), cfg.data.context_frames, cfg.data.image_size
    frames = rng.integers(0, 256, (n, V, K, H, W, 3), dtype=np.uint8)
    state = np.concatenate([rng.normal(0, 0.1, (n, 3)), rng.normal(0, 0.3, (n, 3)), np.full((n, 1), 0.04)], 1)
    return rollout.InitialConditions(frames, state.astype(np.float32), np.arange(n, dtype=np.int32) % 2)


@pytest.fixture(scope="module")
def setup():
    cfg = _cfg()
    ro = rollout.Rollout(cfg, STATS, data_fps=FPS, num_chunks=N)
    params = ro.place_params(_params(cfg))
    policy = simple.linear_policy(jax.random.key(7), len(cfg.data.views), chunk=cfg.rollout.policy_chunk)
    ics = _ics(cfg)
    keys = rollout.episode_keys(0, B)
    ref = ro.run(params, policy, ics, keys, tau=math.inf)
    return cfg, ro, params, policy, ics, keys, ref


def _assert_same(a, b, frame_tol=1, frac=1e-3, atol=1e-5):
    """Same rollout: float outputs to ``atol``; uint8 frames differ by at most ``frame_tol`` levels on a tiny
    fraction of pixels (separately compiled XLA programs may round a value differently)."""
    for k in ("actions", "reread", "states", "u"):
        np.testing.assert_allclose(a[k], b[k], atol=atol, rtol=1e-5, err_msg=k)
    np.testing.assert_array_equal(a["done"], b["done"])
    d = np.abs(a["frames"].astype(int) - b["frames"].astype(int))
    assert d.max() <= frame_tol and np.mean(d > 0) <= frac, (d.max(), np.mean(d > 0))


def test_shapes_and_spec(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    V, (H, W), l = 3, (8, 8), 3
    assert ref["frames"].shape == (B, V, N * l, H, W, 3) and ref["frames"].dtype == np.uint8
    assert ref["actions"].shape == ref["reread"].shape == ref["states"].shape == (B, N * l, 7)
    assert ref["u"].shape == ref["done"].shape == (B, N) and ref["terminated_at"].shape == (B,)
    np.testing.assert_array_equal(ref["initial_frames"], ics.frames)
    assert np.all(np.isfinite(ref["u"])) and np.all(ref["u"] > 0)
    # episodes differ (own keys, own initial conditions): no accidental broadcasting across the batch
    assert not np.allclose(ref["u"][0], ref["u"][1])
    assert ro.chunk_fns.flow_cfg == cfg.flow  # the sampler uses the training's time grid (tiny: t_logit_mean = 1)
    np.testing.assert_allclose(ref["u_raw"], np.linalg.norm(ref["actions"] - ref["reread"], axis=-1)
                               .reshape(B, N, 3).mean(-1), rtol=1e-5)
    # paper defaults: 20 s at 10 Hz with l = 16 -> 13 chunks at frame stride 2 (20 Hz data)
    spec = rollout.make_spec(load_config("paper"), FPS, action_space=DELTA_EE)
    assert (spec.num_chunks, spec.stride, spec.keep, spec.predict, spec.policy_chunk) == (13, 2, 16, 24, 25)
    with pytest.raises(ValueError, match="keep_frames"):
        rollout.make_spec(replace(cfg, rollout=dict(keep_frames=5)), FPS, action_space=DELTA_EE)
    with pytest.raises(ValueError, match="policy_chunk"):  # fewer actions than the 3 frames a chunk keeps
        rollout.make_spec(replace(cfg, rollout=dict(policy_chunk=2)), FPS, action_space=DELTA_EE)


def test_scan_and_host_loop_agree(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    host = ro.run_host(params, as_host(policy), ics, keys, tau=math.inf)
    _assert_same(ref, host)
    # the policy actually uses its rng and its observation: another seed changes the actions
    other = ro.run(params, policy, ics, rollout.episode_keys(1, B), tau=math.inf)
    assert np.abs(other["actions"] - ref["actions"]).max() > 1e-4


def test_a_chunk_shorter_than_the_window_is_held_at_its_last_action(setup):
    """A policy that plans only the kept frames (3 of the 4 predicted) runs: the model's last frame is conditioned on
    the chunk's last action held, in the scan and the host loop alike; fewer than the kept frames is refused."""
    cfg, _, params, policy, ics, keys, _ = setup
    short_cfg = replace(cfg, rollout=dict(policy_chunk=3))
    ro = rollout.Rollout(short_cfg, STATS, data_fps=FPS, num_chunks=N)
    assert (ro.spec.executed, ro.spec.raw_needed, ro.spec.step_actions) == (3, 4, 4)
    first3 = lambda p, o, k: policy.apply(p, o, k)[:3]  # noqa: E731
    short = dataclasses.replace(policy, apply=first3, chunk=3)
    held = dataclasses.replace(policy, apply=lambda p, o, k: rollout.fill_chunk(first3(p, o, k), 4), chunk=4)
    got = ro.run(params, short, ics, keys, tau=math.inf)
    _assert_same(got, ro.run(params, held, ics, keys, tau=math.inf))
    _assert_same(got, ro.run_host(params, as_host(short), ics, keys, tau=math.inf))
    # the held action matters: holding another one changes the (discarded) last frame, hence the kept ones
    moved = dataclasses.replace(policy, apply=lambda p, o, k: jnp.concatenate(
        [first3(p, o, k), first3(p, o, k)[-1:] + 0.5], 0), chunk=4)
    assert np.abs(ro.run(params, moved, ics, keys, tau=math.inf)["frames"].astype(int)
                  - got["frames"].astype(int)).max() > 0
    with pytest.raises(ValueError, match="executes 3"):
        ro.run(params, dataclasses.replace(policy, apply=lambda p, o, k: first3(p, o, k)[:2], chunk=2), ics, keys)


def test_u_chunk_equals_numpy_recomputation(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    a = STATS.normalize(ref["actions"]).reshape(B, N, 3, 7)
    a_hat = STATS.normalize(ref["reread"]).reshape(B, N, 3, 7)
    u = np.linalg.norm(a.astype(np.float64) - a_hat, axis=-1).mean(-1)
    np.testing.assert_allclose(ref["u"], u, rtol=1e-4, atol=1e-5)


def test_inverse_steps_change_only_the_reread(setup):
    """sample.inverse_steps sets the Euler steps of the inverse-dynamics re-read alone: frames, actions and states
    are the forward sampler's (same keys), only the re-read actions and U move."""
    cfg, ro, params, policy, ics, keys, ref = setup
    assert ro.spec.inverse_steps is None  # default: the forward sampler's steps
    fewer = rollout.Rollout(replace(cfg, sample=dict(inverse_steps=1)), STATS, data_fps=FPS, num_chunks=N)
    assert fewer.spec.inverse_steps == 1
    out = fewer.run(params, policy, ics, keys, tau=math.inf)
    for k in ("frames", "actions", "states"):
        np.testing.assert_array_equal(out[k], ref[k], err_msg=k)
    assert np.abs(out["reread"] - ref["reread"]).max() > 1e-4 and not np.allclose(out["u"], ref["u"])


def test_termination_at_first_chunk_above_tau(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    assert ref["tau_units"] == cfg.rollout.tau_units == "raw"  # the paper's units by default
    u = ref["u_raw"]
    assert np.all(ref["terminated_at"] == -1) and ref["termination_rate"] == 0.0  # tau = inf never stops
    # a tau between two of episode 0's chunk values such that it stops after at least one valid chunk
    c_max = int(np.argmax(u[0]))
    if c_max == 0:  # make chunk 0 pass: tau just above u[0, 0], stop at the first later chunk above it
        tau = float(u[0, 0]) + 1e-4
        assert np.any(u[0, 1:] > tau), "need a later chunk above the first one"
    else:
        tau = float((u[0, :c_max].max() + u[0, c_max]) / 2)
    expect = results.terminated_at(u, tau)
    assert expect[0] >= 1
    out = ro.run(params, policy, ics, keys, tau=tau)
    np.testing.assert_array_equal(out["terminated_at"], expect)
    assert out["termination_rate"] == pytest.approx(termination_rate(out["done"])) == np.mean(expect >= 0)
    for b in range(B):
        c = expect[b] if expect[b] >= 0 else N
        assert np.all(~out["done"][b, :c]) and np.all(out["done"][b, c:])
        assert np.all(out["frame_valid"][b] == (np.arange(N * 3) < c * 3))
        upto = min(c + 1, N)  # up to and including the terminating chunk the rollout equals the untruncated one
        np.testing.assert_allclose(out["u_raw"][b, :upto], u[b, :upto], atol=1e-5)
        np.testing.assert_array_equal(out["frames"][b, :, :upto * 3], ref["frames"][b, :, :upto * 3])
        if c < N - 1:  # after termination the state (and context) is frozen: later chunks start from the same state
            base = out["states"][b, c * 3 - 1] if c > 0 else ics.state[b]
            for cc in range(c + 1, N):
                acts = jnp.asarray(out["actions"][b, cc * 3:cc * 3 + 3])
                _, st = imagination_state.integrate(jnp.asarray(base), acts, DELTA_EE)
                np.testing.assert_allclose(out["states"][b, cc * 3:cc * 3 + 3], st, atol=1e-6)
    # the host loop terminates the same way; skip_done stops querying finished episodes but keeps every valid chunk
    calls = []

    class Counting:
        chunk = policy.chunk

        def __init__(self):
            self.inner = as_host(policy)

        def infer(self, obs, rng=None):
            calls.append(1)
            return self.inner.infer(obs, rng=rng)

    host = ro.run_host(params, Counting(), ics, keys, tau=tau, skip_done=True)
    np.testing.assert_array_equal(host["terminated_at"], expect)
    assert len(calls) == sum(min(c + 1, N) if c >= 0 else N for c in expect)
    for b in range(B):
        upto = (expect[b] + 1 if expect[b] >= 0 else N) * 3
        np.testing.assert_allclose(host["actions"][b, :upto], out["actions"][b, :upto], atol=1e-6)
    # tau = 0: every episode stops at chunk 0
    zero = ro.run(params, policy, ics, keys, tau=0.0)
    assert np.all(zero["terminated_at"] == 0) and zero["termination_rate"] == 1.0


def test_tau_units_decide_which_u_is_compared(setup):
    """rollout.tau_units picks the U that termination reads: a tau between the chunk's raw and normalised U stops the
    chunk in exactly one of the two conventions."""
    cfg, ro, params, policy, ics, keys, ref = setup
    B_, frames, state, task, k = ro._inputs(ics, keys)
    acts = ro._pad(np.random.default_rng(0).normal(0, 0.01, (len(k), 5, 7)).astype(np.float32), len(k))
    params = ro.place_params(params)
    _, emit = ro._model_step(params, ro._init(frames, *state), acts, k, jnp.float32(math.inf))
    u, u_raw = np.asarray(emit["u"])[:B_], np.asarray(emit["u_raw"])[:B_]
    assert np.all(u > 10 * u_raw)  # std 0.01: normalised U is ~100x the raw one
    tau = float(np.sqrt(u.min() * u_raw.max()))  # between every raw and every normalised U
    norm = rollout.Rollout(replace(cfg, rollout=dict(tau_units="normalised")), STATS, data_fps=FPS, num_chunks=N)
    for r, stops in ((ro, False), (norm, True)):
        c, _ = r._model_step(params, r._init(frames, *state), acts, k, jnp.float32(tau))
        assert np.all(np.asarray(c.done)[:B_] == stops)
    with pytest.raises(ValueError, match="tau_units"):
        rollout.make_spec(replace(cfg, rollout=dict(tau_units="metres")), FPS, action_space=DELTA_EE)


def test_context_unchanged_by_terminating_chunk(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    B_, frames, state, task, k = ro._inputs(ics, keys)
    carry = ro._init(frames, *state)
    acts = ro._pad(np.random.default_rng(0).normal(0, 0.01, (len(k), 5, 7)).astype(np.float32), len(k))
    params = ro.place_params(params)
    stop, emit = ro._model_step(params, carry, acts, k, jnp.float32(-1.0))  # every U > -1
    go, _ = ro._model_step(params, carry, acts, k, jnp.float32(math.inf))
    assert np.all(stop.done) and not np.any(go.done)
    np.testing.assert_array_equal(stop.context, carry.context)
    np.testing.assert_array_equal(stop.state, carry.state)
    assert not np.allclose(go.context, carry.context)
    # the pushed context is the last K frames of [context, kept l frames]: here l = 3 >= K = 2
    np.testing.assert_array_equal(np.asarray(to_uint8(go.context[:B_])), np.asarray(emit["frames"][:B_, :, 1:]))


def test_cached_and_uncached_rollouts_agree(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    assert cfg.model.context_attention == "causal" and ro.chunk_fns.cache  # -> cached by default
    uncached = rollout.Rollout(cfg, STATS, data_fps=FPS, num_chunks=N, cache=False)
    _assert_same(ref, uncached.run(params, policy, ics, keys, tau=math.inf), atol=2e-5)


def test_batch_composition_and_sharding_do_not_change_an_episode(setup):
    cfg, ro, params, policy, ics, keys, ref = setup
    one = rollout.InitialConditions(ics.frames[1:2], ics.state[1:2], ics.task[1:2])
    alone = ro.run(params, policy, one, keys[1:2], tau=math.inf)
    _assert_same({k: v[1:2] for k, v in ref.items() if isinstance(v, np.ndarray)}, alone)


def test_imagination_state_matches_numpy_rotations():
    rng = np.random.default_rng(0)
    s0 = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 0.8, [0.03]]).astype(np.float32)
    acts = np.concatenate([rng.normal(0, 0.01, (6, 3)), rng.normal(0, 0.2, (6, 3)), rng.uniform(0, 0.08, (6, 1))],
                          1).astype(np.float32)
    acts[2, 3:6] = 0.0  # zero rotation
    final, states = imagination_state.integrate(jnp.asarray(s0), jnp.asarray(acts), DELTA_EE)
    s = s0.astype(np.float64)
    for i, a in enumerate(acts):
        s = np.concatenate([s[:3] + a[:3], rotations.compose_rotvec(a[3:6], s[3:6]), a[6:7]])
        np.testing.assert_allclose(states[i], s, atol=2e-5)
    np.testing.assert_allclose(final, states[-1])


def _store(tmp_path, n=B):
    from sc3_jax.data import synthetic

    return synthetic.generate(tmp_path / "eps", n, length=40, image_size=(8, 8), seed=0, progress=False)


def test_offline_replay_with_recorded_actions(tmp_path, setup):
    cfg, ro_closed, params, *_ = setup
    store = _store(tmp_path)
    ro = rollout.Rollout(cfg, STATS, data_fps=store.fps, num_chunks=N)
    eps = [store.load(e) for e in store.episode_ids()]
    assert min(rollout.max_offline_chunks(ep.length, ro.spec) for ep in eps) == 6  # (40 // 2 - 2) // 3
    items = [rollout.from_episode(ep, store.views, ro.spec) for ep in eps]
    ics = rollout.stack_initial_conditions([it[0] for it in items])
    actions, targets = np.stack([it[1] for it in items]), np.stack([it[2] for it in items])
    # recorded frames at stride 2: context = frames 0, 2; targets = frames 4, 6, ...; action i composes 2 steps
    np.testing.assert_array_equal(ics.frames[0, 0], eps[0].frames["left"][[0, 2]])
    np.testing.assert_array_equal(targets[0, 0, :2], eps[0].frames["left"][[4, 6]])
    np.testing.assert_allclose(ics.state[0], eps[0].ee_pose[2])
    np.testing.assert_allclose(actions[0, 1, 0, :3], eps[0].actions[2 + 2 * 3: 2 + 2 * 3 + 2, :3].sum(0), atol=1e-6)
    with pytest.raises(ValueError, match="too few"):
        rollout.from_episode(eps[0], store.views,
                             rollout.make_spec(cfg, store.fps, num_chunks=7, action_space=DELTA_EE))
    out = ro.run_offline(params, ics, actions, rollout.episode_keys(0, B))
    np.testing.assert_allclose(out["actions"], actions[:, :, :3].reshape(B, N * 3, 7))
    assert "psnr" not in out  # scoring is the caller's (measures.metrics)
    per_frame, per_view = psnr_by_view(out["frames"], targets, out["frame_valid"])
    assert per_frame.shape == (B, 3, N * 3) and np.all(np.isfinite(per_frame))
    np.testing.assert_allclose(per_frame, psnr(out["frames"], targets), rtol=1e-5)
    np.testing.assert_allclose(per_view, per_frame.mean(-1), rtol=1e-5)
    # chunk_actions (the sweep's offline actions) builds the same per-chunk arrays from the recorded actions
    np.testing.assert_array_equal(rollout.chunk_actions(eps[0].actions[2:], ro.spec), actions[0])
    assert np.all(out["terminated_at"] == -1)


def test_cli_writes_arrays_and_videos(tmp_path, setup, capsys):
    """`sc3 rollout` end to end; its sampler is the sweep's (SweepConfig's defaults), not the checkpoint's 3 steps."""
    import dataclasses
    import json

    import cv2

    from sc3_jax.train import train
    from sc3_jax.cli import main
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig

    cfg = replace(setup[0], data=dict(path=str(tmp_path / "eps")), sample=dict(steps=3),
                  train=dict(workdir=str(tmp_path / "run"), async_checkpointing=False))
    _store(tmp_path)
    mngr = train.checkpoint_manager(cfg)
    train.save(mngr, 0, train.init_state(cfg), {"iterator": {}}, force=True)
    mngr.wait_until_finished()
    STATS.save(tmp_path / "run" / "norm_stats.json")
    (tmp_path / "run" / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    assert config_from_dict(json.loads((tmp_path / "run" / "config.json").read_text())) == cfg
    # N chunks of l = 3 frames at 10 Hz: 0.9 s (what --num-chunks N said before the config's own fields)
    rc = main(["rollout", "--world-model", str(tmp_path / "run"), "--policy", "linear", "--data",
               str(tmp_path / "eps"), "--out", str(tmp_path / "out"), "--rollout.episode-seconds", "0.9",
               "--rollout.tau", "inf", "--offline", "--benchmark", "bussing", "--no-progress"])
    assert rc == 0
    z = np.load(tmp_path / "out" / "rollout.npz")
    assert z["frames"].shape == (B, 3, N * 3, 8, 8, 3) and z["u"].shape == (B, N)
    assert list(z["episode_ids"]) == ["ep000000", "ep000001", "ep000002"]
    off = np.load(tmp_path / "out" / "offline.npz")
    assert off["psnr"].shape == (B, 3, N * 3)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["termination_rate"] == 0.0 and set(summary["offline_psnr_per_view"]) == {"left", "right", "wrist"}
    sweep = SweepConfig()
    assert (summary["sample_steps"], summary["inverse_steps"]) == (sweep.sample_steps, sweep.inverse_steps)
    assert summary["u_mean"] == pytest.approx(float(z["u_raw"].mean()))  # raw units, every chunk ran
    assert summary["stopped"] == 0 and not summary["success"]["available"]  # 8x8 frames: not the scorer's
    out = capsys.readouterr().out
    assert "stopped at tau = inf: 0 of 3 episodes" in out and "no success estimate: the perception scorer" in out
    assert out.strip().splitlines()[-1].startswith(f"wrote {tmp_path / 'out'}/: rollout.npz, summary.json")
    cap = cv2.VideoCapture(str(tmp_path / "out" / "ep000000_left.mp4"))
    count = 0
    while cap.read()[0]:
        count += 1
    assert count == 2 + N * 3  # context + kept frames


def test_policy_rate_actions_are_composed_to_the_model_rate():
    """policy_hz = 2 x control_hz: the model sees pairs of raw actions composed (as the data pipeline composes
    recorded actions for strided windows); the state integrates every raw action and is read at the kept frames."""
    from sc3_jax.data.pipeline import compose_actions
    rng = np.random.default_rng(1)
    raw = np.concatenate([rng.normal(0, 0.01, (8, 3)), rng.normal(0, 0.2, (8, 3)), rng.uniform(0, 0.08, (8, 1))],
                         1).astype(np.float32)
    got = np.asarray(imagination_state.compose(jnp.asarray(raw), 2, DELTA_EE))
    want = np.stack([compose_actions(raw, i, 2, DELTA_EE) for i in range(0, 8, 2)])
    np.testing.assert_allclose(got, want, atol=2e-5)
    cfg = replace(_cfg(), rollout=dict(policy_chunk=8, keep_frames=3, policy_hz=20.0, control_hz=10.0))
    ro = rollout.Rollout(cfg, STATS, data_fps=FPS, num_chunks=2)
    assert (ro.spec.ratio, ro.spec.raw_needed) == (2, 8)
    policy = simple.linear_policy(jax.random.key(7), len(cfg.data.views), chunk=8, noise=0.0)
    out = ro.run(ro.place_params(_params(cfg)), policy, _ics(cfg), rollout.episode_keys(0, B), tau=math.inf)
    assert out["actions"].shape == (B, 2 * 3, 7) and out["states"].shape == (B, 2 * 3, 7)
    # the state after kept frame j of chunk 0 integrates raw actions 0 .. 2j+1 of that chunk's proposal
    host = as_host(policy)
    obs = {"images": _ics(cfg).frames[0][:, -1], "state": _ics(cfg).state[0], "task": np.int32(0)}
    a0 = np.asarray(host.infer(obs), np.float32)
    _, states = imagination_state.integrate(jnp.asarray(_ics(cfg).state[0]), jnp.asarray(a0[:6]), DELTA_EE)
    np.testing.assert_allclose(out["states"][0, :3], np.asarray(states)[1::2], atol=1e-5)
    np.testing.assert_allclose(out["actions"][0, :3],
                               np.stack([compose_actions(a0, i, 2, DELTA_EE) for i in (0, 2, 4)]),
                               atol=2e-5)
    with pytest.raises(ValueError, match="policy_chunk=5"):
        rollout.make_spec(replace(cfg, rollout=dict(policy_chunk=5)), FPS, action_space=DELTA_EE)
