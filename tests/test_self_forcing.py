"""Self-forced context (flow.self_forcing): a picked forward-dynamics sample trains on a rollout's next chunk, its
context the model's own one-step prediction, held constant for autodiff. Off, training is exactly what it was."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import flow, modes, sharding
from sc3_jax.train import train
from sc3_jax.core.config import (Config, DataConfig, FlowConfig, MeshConfig, ModelConfig, RolloutConfig, TrainConfig,
                            replace)
from sc3_jax.data import synthetic
from sc3_jax.core.errors import UserError
from sc3_jax.model import dit

from _training_checks import assert_resumed_like_straight, assert_same_training

K, T, L = 2, 3, 2  # context frames, future frames, rollout.keep_frames (the shift)
V, P_, D = 3, 4, 48  # views, tokens per frame (8x8 images, 4x4 patches), token width
GRID = (2, 2)


def small(self_forcing: float = 0.0, mesh=(1, 1, 1)) -> Config:
    """Pose conditioning and context noise on, so self-forcing is checked together with both."""
    return Config(model=ModelConfig(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                    rope_axes_dim=(2, 3, 3), pose_conditioning=True, context_noise=True),
                  data=DataConfig(image_size=(8, 8), context_frames=K, future_frames=T, batch_size=8),
                  flow=FlowConfig(context_noise_max=0.3, self_forcing=self_forcing),
                  train=TrainConfig(lr=1e-3, warmup_steps=1, steps=10, progress=False, tensorboard=False,
                                    async_checkpointing=False),
                  rollout=RolloutConfig(keep_frames=L),
                  mesh=MeshConfig(*mesh))


MCFG = small().model


def random_batch(cfg: Config, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    for k, s in train.batch_shapes(cfg).items():
        if s.dtype == np.uint8:
            out[k] = rng.integers(0, 256, s.shape, dtype=np.uint8)
        elif np.issubdtype(s.dtype, np.integer):
            out[k] = rng.integers(1, 3, s.shape).astype(s.dtype)
        else:
            out[k] = rng.normal(size=s.shape).astype(s.dtype)
    return out


def _params(key):
    p = dit.init_params(MCFG, D, key, GRID)
    # non-zero output heads, so the prediction (and the loss) depends on every input and parameter
    return jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(1), x.shape), p)


def _extended(key, B, shift):
    """Tokens of windows extended by ``shift`` frames, as train.window_data reads them."""
    ks = jax.random.split(key, 3)
    return (jax.random.normal(ks[0], (B, V, K + T + shift, P_, D)), jax.random.normal(ks[1], (B, T + shift, 7)),
            jax.random.normal(ks[2], (B, T + shift + 1, 7)))


def _loss_without_self_forcing(params, cfg, video, actions, stride, rng, probs, grid, fcfg=FlowConfig(),
                               context_frames=None, pose=None, **_):
    """flow.loss as it was before self-forcing existed (verbatim): the reference the off switch must equal."""
    from sc3_jax.model.flow import draw_t, masked_loss, noise_context, noise_inputs, predict
    B, V, F = video.shape[:3]
    T = actions.shape[1]
    K = F - T if context_frames is None else context_frames
    k_mode, k_t, k_ev, k_ea = jax.random.split(rng, 4)
    clean = video
    context_level = None
    if fcfg.context_noise_max > 0:
        k_cl, k_cn = jax.random.split(jax.random.fold_in(rng, 7))
        context_level = jax.random.uniform(k_cl, (B,), jnp.float32, 0.0, fcfg.context_noise_max)
        video = noise_context(video, context_level, k_cn, K)
    mode, kept = modes.draw(k_mode, B, V, probs)
    video_noisy, action_noisy = modes.masks(mode, kept, V, K, F - K, T)
    t = draw_t(k_t, B, fcfg)
    eps_v = jax.random.normal(k_ev, video.shape, video.dtype)
    eps_a = jax.random.normal(k_ea, actions.shape, actions.dtype)
    inp = noise_inputs(video, actions, stride, video_noisy, action_noisy, t, eps_v, eps_a, pose, context_level)
    (v_v, v_a), (x0_v, x0_a) = predict(params, cfg, inp, grid, context_frames=context_frames)
    if cfg.prediction == "velocity":
        preds, targets = (v_v, v_a), (eps_v[:, :, K:] - clean[:, :, K:], eps_a - actions)
    else:
        preds, targets = (x0_v, x0_a), (clean[:, :, K:], actions)
    total, per_sample = masked_loss(*preds, *targets, video_noisy[:, :, K:], action_noisy,
                                    (fcfg.video_loss_weight, fcfg.action_loss_weight))
    metrics = {"loss": total}
    for m, name in enumerate(modes.NAMES):
        sel = (mode == m).astype(jnp.float32)
        metrics[f"loss_{name}"] = jnp.sum(per_sample * sel) / jnp.maximum(jnp.sum(sel), 1.0)
        metrics[f"frac_{name}"] = jnp.mean(sel)
    return total, metrics


def test_off_trains_exactly_as_without_the_feature(monkeypatch):
    """self_forcing = 0 (the default): same windows, and three train steps give bit-identical params and metrics
    (same keys: no self-forcing entries) to the step built on the loss without the feature."""
    cfg = small()
    assert cfg.flow.self_forcing == FlowConfig().self_forcing == 0.0
    assert train.window_data(cfg) is cfg.data and train.batch_shapes(cfg)["frames"].shape[2] == K + T
    batches = [random_batch(cfg, seed) for seed in range(3)]

    def run():
        step = jax.jit(train.make_train_step(cfg))
        state, rows = train.init_state(cfg), []
        for b in batches:
            state, metrics = step(state, b)
            rows.append(jax.device_get(metrics))
        return jax.device_get(state["params"]), rows

    now = run()
    monkeypatch.setattr(flow, "loss", _loss_without_self_forcing)
    assert_same_training(now, run())


@pytest.mark.parametrize("shift", [1, 3])
def test_a_picked_sample_is_the_rollouts_next_chunk(shift):
    """Picked: the window `shift` frames later, its context the last K of [real context, the sampler's one-step
    prediction of the first `shift` future frames] (rollout.py's context update), its actions / poses the later
    ones, its targets real frames. Unpicked or not eligible: the first K + T frames, untouched."""
    B = 8
    params = _params(jax.random.key(0))
    video, actions, pose = _extended(jax.random.key(2), B, shift)
    stride = jnp.ones((B,), jnp.int32)
    eligible = jnp.array([True, True, True, True, True, False, True, False])
    rng = jax.random.key(3)
    window = jax.jit(lambda p, *a: flow.self_forced_window(p, MCFG, *a[:4], GRID, FlowConfig(self_forcing=0.5),
                                                           shift, *a[4:]))  # jitted: one compile, not one per op
    v2, a2, p2, _, picked = window(params, video, actions, stride, rng, eligible, pose)
    picked = np.asarray(picked)
    assert not picked[~np.asarray(eligible)].any()
    assert picked.any() and (~picked & np.asarray(eligible)).any(), "this key picks all or none: choose another"
    vn, an = modes.fixed(modes.FD, B, V, K, T)
    predicted, _ = jax.jit(lambda p, *a: flow.sample(p, MCFG, *a, 1, GRID, cache="none", pose=pose[:, :T + 1]))(
        params, video[:, :, :K + T], actions[:, :T], stride, vn, an, jax.random.split(rng)[1])
    fed = jnp.concatenate([video[:, :, :K], predicted[:, :, K:K + shift]], axis=2)[:, :, -K:]
    for b in range(B):
        if picked[b]:
            np.testing.assert_allclose(v2[b, :, :K], fed[b], rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(v2[b, :, K:], video[b, :, shift + K:shift + K + T])
            np.testing.assert_array_equal(a2[b], actions[b, shift:])
            np.testing.assert_array_equal(p2[b], pose[b, shift:])
            # the predicted frames are not the real ones (else this checks nothing)
            assert float(jnp.abs(v2[b, :, K - 1] - video[b, :, shift + K - 1]).max()) > 1e-3
        else:
            np.testing.assert_array_equal(v2[b], video[b, :, :K + T])
            np.testing.assert_array_equal(a2[b], actions[b, :T])
            np.testing.assert_array_equal(p2[b], pose[b, :T + 1])


def test_no_gradient_flows_through_the_self_forced_context():
    """The gradient of the self-forced loss equals the gradient of the ordinary loss with the self-forced window
    fed in as a constant; the loss differs from the loss on the real window with the same key."""
    B = 4
    params = _params(jax.random.key(4))
    video, actions, pose = _extended(jax.random.key(5), B, L)
    stride = jnp.ones((B,), jnp.int32)
    rng = jax.random.key(6)
    on = FlowConfig(context_noise_max=0.3, self_forcing=1.0)
    off = replace(on, self_forcing=0.0)
    fd = (1.0, 0.0, 0.0)  # every sample forward dynamics, so every one is picked

    def forced_loss(p):
        return flow.loss(p, MCFG, video, actions, stride, rng, fd, GRID, on, pose=pose, self_forcing_shift=L)

    (loss_on, metrics), grads = jax.jit(jax.value_and_grad(forced_loss, has_aux=True))(params)
    assert float(metrics["frac_self_forced"]) == 1.0
    v2, a2, p2, _, picked = jax.jit(lambda p: flow.self_forced_window(
        p, MCFG, video, actions, stride, jax.random.fold_in(rng, 11), GRID, on, L, jnp.ones((B,), bool), pose))(params)
    assert bool(picked.all())

    def const_loss(p, v):
        return flow.loss(p, MCFG, v, a2, stride, rng, fd, GRID, off, pose=p2)[0]

    loss_const, (const_grads, d_video) = jax.jit(jax.value_and_grad(const_loss, argnums=(0, 1)))(params, v2)
    assert float(loss_on) == pytest.approx(float(loss_const), rel=1e-6)
    for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(const_grads)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-8)
    # the check can fail: the loss reads the substituted context, which the params made
    assert float(jnp.abs(d_video[:, :, :K]).max()) > 0
    real = jax.jit(lambda p: flow.loss(p, MCFG, video[:, :, :K + T], actions[:, :T], stride, rng, fd, GRID, off,
                                       pose=pose[:, :T + 1])[0])(params)
    assert abs(float(loss_on) - float(real)) > 1e-6


def _one_step(cfg: Config, devices):
    mesh = sharding.make_mesh(cfg.mesh, devices)
    step, _ = train.compile_train_step(cfg, mesh)
    state = train.create_state(cfg, mesh)
    state, metrics = step(state, sharding.global_batch(mesh, random_batch(cfg)))
    return jax.device_get(metrics), jax.device_get(state["params"])


@pytest.mark.slow  # compiles a sharded and a one-device train step: the default run stays under 15 min
def test_sharded_step_matches_one_device_and_reports_the_fraction():
    cfg = small(0.5)
    assert train.batch_shapes(cfg)["frames"].shape[2] == K + T + L  # windows grow by keep_frames
    assert train.batch_shapes(cfg)["pose"].shape[1] == T + L + 1
    ref_metrics, ref_params = _one_step(cfg, jax.devices()[:1])
    metrics, params = _one_step(small(0.5, (4, 2, 1)), jax.devices())
    assert len(jax.devices()) == 8
    assert float(metrics["loss"]) == pytest.approx(float(ref_metrics["loss"]), rel=1e-5)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert float(metrics["frac_self_forced"]) == float(ref_metrics["frac_self_forced"])
    assert 0 < float(metrics["frac_self_forced"]) <= float(metrics["frac_forward"])


@pytest.mark.slow  # trains, stops and resumes: the default run stays under 15 min
def test_resume_is_exact_and_keeps_the_shift(tmp_path):
    """Two steps, stop, resume to four: every metric of every step equals an uninterrupted run's (one device: the
    sharded step is the test above); a resume that changes rollout.keep_frames (the windows' shift) is refused."""
    synthetic.generate(tmp_path / "episodes", 3, length=30, image_size=(8, 8), seed=0, progress=False)
    mesh = sharding.make_mesh(MeshConfig(1, 1, 1), jax.devices()[:1])

    def cfg(name):
        return replace(small(0.5), data=dict(path=str(tmp_path / "episodes")),
                       train=dict(workdir=str(tmp_path / name), steps=4, ckpt_every=2, log_every=1))

    train.train(cfg("straight"), mesh)
    train.train(cfg("resumed"), mesh, stop_at=2)
    assert sorted(train.read_metrics(tmp_path / "resumed")) == [1, 2]
    train.train(cfg("resumed"), mesh)
    assert_resumed_like_straight(tmp_path / "straight", tmp_path / "resumed", "frac_self_forced")
    with pytest.raises(UserError, match="rollout.keep_frames"):
        train.check_workdir(replace(cfg("resumed"), rollout=dict(keep_frames=1)))
    train.check_workdir(replace(cfg("resumed"), rollout=dict(tau=0.05)))  # other rollout settings may change


def test_user_errors():
    with pytest.raises(UserError, match="flow.self_forcing"):
        train.batch_shapes(small(1.5))
    with pytest.raises(UserError, match="rollout.keep_frames"):
        train.batch_shapes(replace(small(0.5), rollout=dict(keep_frames=T + 1)))
