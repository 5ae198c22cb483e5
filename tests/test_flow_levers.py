"""Training-recipe levers of the rectified flow, all off by default: flow from the present (flow.from_present: a
noisy future frame flows from its view's last context frame plus scaled noise, not from pure noise), per-frame noise
levels (flow.per_frame_t, diffusion forcing: each future frame and its action draw their own t in training) and a
video loss weighted toward what moves (flow.moving_weight). Off, the loss is exactly what it was."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.model import flow, modes
from sc3_jax.train import train
from sc3_jax.commands import parse_with_config
from sc3_jax.core.config import Config, DataConfig, FlowConfig, ModelConfig, TrainConfig, config_from_dict, load_config
from sc3_jax.model import dit

K, T = 2, 3  # context and future frames
V, P_, D = 3, 4, 48  # views, tokens per frame (8x8 images, 4x4 patches), token width
GRID = (2, 2)
SMALL = dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64, rope_axes_dim=(2, 3, 3))
MCFG = ModelConfig(**SMALL, context_noise=True)  # residual prediction (the default)
PROBS = (0.4, 0.3, 0.3)  # every mode in a batch of 16


def _tokens(B, seed=0):
    kv, ka = jax.random.split(jax.random.key(seed))
    return jax.random.normal(kv, (B, V, K + T, P_, D)), jax.random.normal(ka, (B, T, 7)), jnp.ones((B,), jnp.int32)


def _perturbed(cfg, seed=0):
    p = dit.init_params(cfg, D, jax.random.key(seed), GRID)
    return jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(seed + 1), x.shape), p)


def _noise_inputs_before(video, actions, stride, video_noisy, action_noisy, t, eps_video, eps_actions, pose=None,
                         context_level=None, anchor_gap=None):
    """flow.noise_inputs as it was before the levers (verbatim)."""
    tv = jnp.where(video_noisy, t[:, None, None], 0.0)
    ta = jnp.where(action_noisy, t[:, None], 0.0)
    xv = jnp.where(video_noisy[..., None, None], (1 - tv[..., None, None]) * video + tv[..., None, None] * eps_video,
                   video)
    xa = jnp.where(action_noisy[..., None], (1 - ta[..., None]) * actions + ta[..., None] * eps_actions, actions)
    return dit.Inputs(xv, xa, tv, video_noisy, ta, action_noisy, stride, pose=pose, context_level=context_level,
                      anchor_gap=anchor_gap)


def _loss_before(params, cfg, video, actions, stride, rng, probs, grid, fcfg):
    """flow.loss as it was before the levers (verbatim, without self-forcing): the reference the off switches must
    equal bit for bit."""
    B, V, F = video.shape[:3]
    T = actions.shape[1]
    K = F - T
    k_mode, k_t, k_ev, k_ea = jax.random.split(rng, 4)
    clean = video
    k_cl, k_cn = jax.random.split(jax.random.fold_in(rng, 7))
    context_level = jax.random.uniform(k_cl, (B,), jnp.float32, 0.0, fcfg.context_noise_max)
    video = flow.noise_context(video, context_level, k_cn, K)
    mode, kept = modes.draw(k_mode, B, V, probs)
    video_noisy, action_noisy = modes.masks(mode, kept, V, K, F - K, T)
    t = jnp.clip(jax.nn.sigmoid(fcfg.t_logit_mean + fcfg.t_logit_std * jax.random.normal(k_t, (B,))), 1e-3, 1.0)
    eps_v = jax.random.normal(k_ev, video.shape, video.dtype)
    eps_a = jax.random.normal(k_ea, actions.shape, actions.dtype)
    inp = _noise_inputs_before(video, actions, stride, video_noisy, action_noisy, t, eps_v, eps_a, None,
                               context_level)
    (v_v, v_a), (x0_v, x0_a) = flow.predict(params, cfg, inp, grid)
    if cfg.prediction == "velocity":
        preds, targets = (v_v, v_a), (eps_v[:, :, K:] - clean[:, :, K:], eps_a - actions)
    else:
        preds, targets = (x0_v, x0_a), (clean[:, :, K:], actions)
    total, per_sample = flow.masked_loss(*preds, *targets, video_noisy[:, :, K:], action_noisy,
                                         (fcfg.video_loss_weight, fcfg.action_loss_weight))
    metrics = {"loss": total}
    for m, name in enumerate(modes.NAMES):
        sel = (mode == m).astype(jnp.float32)
        metrics[f"loss_{name}"] = jnp.sum(per_sample * sel) / jnp.maximum(jnp.sum(sel), 1.0)
        metrics[f"frac_{name}"] = jnp.mean(sel)
    return total, metrics


@pytest.mark.parametrize("prediction", ["residual", "velocity"])
def test_off_the_loss_is_bit_identical_to_before(prediction):
    """Defaults and the levers spelled off (from_present 0, per_frame_t False) give the loss and every metric of the
    code before the levers, bit for bit; off, the sampler's source is the noise itself."""
    cfg = dataclasses.replace(MCFG, prediction=prediction)
    fcfg = FlowConfig(context_noise_max=0.3)
    assert (fcfg.from_present, fcfg.per_frame_t, fcfg.moving_weight) == (0.0, False, 0.0)
    params = _perturbed(cfg)
    video, actions, stride = _tokens(16)
    rng = jax.random.key(3)
    now, spelled, before = jax.jit(lambda p: (
        flow.loss(p, cfg, video, actions, stride, rng, PROBS, GRID, fcfg),
        flow.loss(p, cfg, video, actions, stride, rng, PROBS, GRID,
                  dataclasses.replace(fcfg, from_present=0.0, per_frame_t=False, moving_weight=0.0)),
        _loss_before(p, cfg, video, actions, stride, rng, PROBS, GRID, fcfg)))(params)
    for got in (now, spelled):
        assert got[1].keys() == before[1].keys()
        for k in before[1]:
            np.testing.assert_array_equal(got[1][k], before[1][k], err_msg=k)
    eps = jnp.ones((1, V, K + T, P_, D))
    assert flow.flow_source(video[:1], jnp.ones((1, V, K + T), bool), eps, K, 0.0) is eps


def test_from_present_flows_from_the_last_context_frame_where_it_is_clean():
    """anchor + sigma eps for the future frames of the views whose last context frame is clean, eps elsewhere."""
    video, _, _ = _tokens(2)
    eps = jax.random.normal(jax.random.key(9), video.shape)
    noisy = jnp.zeros((2, V, K + T), bool).at[:, :, K:].set(True).at[0, 1, K - 1].set(True)  # view 1's anchor noisy
    src = flow.flow_source(video, noisy, eps, K, 0.25)
    for b in range(2):
        for v in range(V):
            want = eps[b, v, K:] if (b, v) == (0, 1) else video[b, v, K - 1] + 0.25 * eps[b, v, K:]
            np.testing.assert_allclose(src[b, v, K:], want, rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(src[b, v, :K], eps[b, v, :K])  # never read (clean), left as drawn


def test_from_present_at_t_1_the_loss_sees_anchor_plus_noise_and_targets_its_velocity(monkeypatch):
    """In flow.loss at t = 1 every noisy future video token is anchor + sigma eps, the anchor its view's last
    context frame as the model sees it (context-noised); actions keep pure noise; the velocity target is
    anchor + sigma eps - x (a prediction of it has zero loss, the old target eps - x does not)."""
    sigma, B = 0.3, 16
    cfg = dataclasses.replace(MCFG, prediction="velocity")
    fcfg = FlowConfig(context_noise_max=0.3, from_present=sigma)
    video, actions, stride = _tokens(B, 1)
    rng = jax.random.key(4)
    _, _, k_ev, k_ea = jax.random.split(rng, 4)  # flow.loss's noise keys
    eps_v, eps_a = jax.random.normal(k_ev, video.shape), jax.random.normal(k_ea, actions.shape)
    monkeypatch.setattr(flow, "draw_t", lambda rng, batch, fcfg, frames=None: jnp.ones((batch,)))
    seen = {}

    def predict(params, cfg, inp, grid, context_kv=None, context_frames=None, target="new"):
        seen["inp"] = inp
        src = inp.video[:, :, K - 1:K] + sigma * eps_v[:, :, K:]
        v_v = (src if target == "new" else eps_v[:, :, K:]) - video[:, :, K:]
        return (v_v, eps_a - actions), (None, None)

    monkeypatch.setattr(flow, "predict", predict)
    loss, metrics = flow.loss(None, cfg, video, actions, stride, rng, PROBS, GRID, fcfg)
    inp = seen["inp"]
    assert all(float(metrics[f"frac_{n}"]) > 0 for n in modes.NAMES)
    assert float(jnp.abs(inp.video[:, :, :K] - video[:, :, :K]).max()) > 1e-3  # the context is noised
    fut, vt = np.asarray(inp.video_noisy[:, :, K:]), np.asarray(inp.video_t[:, :, K:])
    assert fut.any() and np.all(vt[fut] == 1.0)
    src = inp.video[:, :, K - 1:K] + sigma * eps_v[:, :, K:]
    np.testing.assert_allclose(np.asarray(inp.video[:, :, K:])[fut], np.asarray(src)[fut], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(inp.video[:, :, K:])[~fut], np.asarray(video[:, :, K:])[~fut])
    an = np.asarray(inp.action_noisy)
    np.testing.assert_allclose(np.asarray(inp.actions)[an], np.asarray(eps_a)[an], rtol=1e-6, atol=1e-6)
    assert float(loss) < 1e-10
    monkeypatch.setattr(flow, "predict", lambda *a, **k: predict(*a, **k, target="old"))
    assert float(flow.loss(None, cfg, video, actions, stride, rng, PROBS, GRID, fcfg)[0]) > 0.01


def test_an_untrained_model_sampled_from_the_present_returns_the_anchor():
    """Residual, zero output (untrained): every future frame is its view's last context frame. Velocity with a zero
    output: the sample is its source, anchor + sigma eps (sigma tiny: nearly the anchor), eps when off -- so the
    sampler starts where the loss's flows start."""
    B, sigma = 2, 1e-3
    video, actions, stride = _tokens(B, 2)
    vn, an = modes.fixed(modes.FD, B, V, K, T)
    rng = jax.random.key(5)
    anchor = jnp.broadcast_to(video[:, :, K - 1:K], video[:, :, K:].shape)

    def run(cfg, params, fcfg):
        return jax.jit(lambda p: flow.sample(p, cfg, video, actions, stride, vn, an, rng, 4, GRID, fcfg=fcfg))(
            params)[0]

    residual = run(MCFG, dit.init_params(MCFG, D, jax.random.key(0), GRID), FlowConfig(from_present=sigma))
    np.testing.assert_allclose(residual[:, :, K:], anchor, atol=1e-5)
    np.testing.assert_array_equal(residual[:, :, :K], video[:, :, :K])
    vcfg = dataclasses.replace(MCFG, prediction="velocity")
    zero = {**dit.init_params(vcfg, D, jax.random.key(0), GRID)}
    zero["proj_out"] = jax.tree.map(jnp.zeros_like, zero["proj_out"])
    on = run(vcfg, zero, FlowConfig(from_present=sigma))
    off = run(vcfg, zero, FlowConfig())
    np.testing.assert_allclose(on[:, :, K:], anchor, atol=10 * sigma)
    np.testing.assert_allclose(on[:, :, K:], anchor + sigma * off[:, :, K:], rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(off[:, :, K:] - anchor).mean()) > 0.5  # off: pure noise, far from the anchor


def test_per_frame_t_gives_each_future_frame_and_its_action_its_own_level(monkeypatch):
    """flow.per_frame_t: the model's video_t varies across the future frames of one sample, is equal across the
    noisy views of one frame (0 on the context and on a kept view), and action i's t is frame i's."""
    B = 16
    fcfg = FlowConfig(per_frame_t=True)
    video, actions, stride = _tokens(B, 3)
    drawn, seen = {}, {}
    draw_t = flow.draw_t

    def spy(*a, **k):
        drawn["t"] = draw_t(*a, **k)
        return drawn["t"]

    def predict(params, cfg, inp, grid, context_kv=None, context_frames=None):
        seen["inp"] = inp
        z = jnp.zeros_like(video[:, :, K:])
        return (z, jnp.zeros_like(actions)), (z, jnp.zeros_like(actions))

    monkeypatch.setattr(flow, "draw_t", spy)
    monkeypatch.setattr(flow, "predict", predict)
    _, metrics = flow.loss(None, MCFG, video, actions, stride, jax.random.key(6), PROBS, GRID, fcfg)
    assert all(float(metrics[f"frac_{n}"]) > 0 for n in modes.NAMES)
    t, inp = np.asarray(drawn["t"]), seen["inp"]
    assert t.shape == (B, T) and np.all((t > 0) & (t <= 1))
    vt, at = np.asarray(inp.video_t), np.asarray(inp.action_t)
    vn, an = np.asarray(inp.video_noisy), np.asarray(inp.action_noisy)
    assert np.all(vt[:, :, :K] == 0)
    for b in range(B):
        np.testing.assert_array_equal(at[b], t[b] if an[b].any() else 0.0)
        for v in range(V):
            np.testing.assert_array_equal(vt[b, v, K:], t[b] if vn[b, v, K:].any() else 0.0)
        assert np.ptp(t[b]) > 1e-3  # the levels differ across frames
    # noise_inputs with per-frame levels: frame i of every view is (1 - t_i) x + t_i eps
    eps = jax.random.normal(jax.random.key(7), video.shape)
    vn, an = modes.fixed(modes.FD, B, V, K, T)
    x = flow.noise_inputs(video, actions, stride, vn, an, jnp.asarray(t), eps, actions).video
    tt = jnp.asarray(t)[:, None, :, None, None]
    np.testing.assert_allclose(x[:, :, K:], (1 - tt) * video[:, :, K:] + tt * eps[:, :, K:], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="one action per future token frame"):  # the Cosmos3 layout: 2 x 3 actions
        flow.loss(None, MCFG, video[:, :, :4], jnp.zeros((B, 6, 7)), stride, jax.random.key(6), PROBS, GRID, fcfg,
                  context_frames=2)


def test_from_present_must_be_finite_and_not_negative():
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="from_present"):
            FlowConfig(from_present=bad)
        with pytest.raises(ValueError, match="moving_weight"):
            FlowConfig(moving_weight=bad)


@settings(max_examples=25, deadline=None)
@given(weight=st.floats(0.5, 20.0), mover=st.integers(0, P_ - 1), seed=st.integers(0, 1000))
def test_moving_weight_counts_an_error_on_the_token_that_moves_more_than_one_on_a_still_token(weight, mover, seed):
    """One token of every future frame moves away from the last context frame, the others stay: the same squared
    error costs more on the mover than on a still token, by the weights' ratio; equal weights give the plain mean."""
    rng = np.random.default_rng(seed)
    clean = np.repeat(rng.normal(size=(1, V, 1, P_, D)), K + T, axis=2).astype(np.float32)
    clean[:, :, K:, mover] += 3.0  # the mover
    w = flow.moving_token_weights(jnp.asarray(clean), K, weight)
    assert w.shape == (1, V, T, P_)
    still = (mover + 1) % P_
    np.testing.assert_allclose(w[..., still], 1.0, atol=1e-5)
    np.testing.assert_allclose(w[..., mover], 1.0 + weight * P_, rtol=1e-4)  # its change over the frame's mean
    target, noisy = jnp.zeros((1, V, T, P_, D)), jnp.ones((1, V, T), bool)
    actions, no_actions = jnp.zeros((1, T, 4)), jnp.zeros((1, T), bool)
    err = lambda tok: jnp.zeros((1, V, T, P_, D)).at[:, :, :, tok].set(1.0)  # noqa: E731
    on_mover, _ = flow.masked_loss(err(mover), actions, target, actions, noisy, no_actions, token_weights=w)
    on_still, _ = flow.masked_loss(err(still), actions, target, actions, noisy, no_actions, token_weights=w)
    np.testing.assert_allclose(float(on_mover) / float(on_still), 1.0 + weight * P_, rtol=1e-4)
    plain, _ = flow.masked_loss(err(mover), actions, target, actions, noisy, no_actions)
    equal, _ = flow.masked_loss(err(mover), actions, target, actions, noisy, no_actions,
                                token_weights=jnp.ones((1, V, T, P_)))
    np.testing.assert_allclose(float(equal), float(plain), rtol=1e-6)


def test_the_levers_are_options_and_saved_with_the_model():
    """`sc3 train --flow.from-present 0.1 --flow.per-frame-t` parses; config.json keeps both (what rollouts and
    sweeps read the sampler's source from), and a config.json from before them reads as off."""
    from sc3_jax.commands.train import Args
    _, cfg = parse_with_config(Args, ["--config", "tiny", "--flow.from-present", "0.1", "--flow.per-frame-t"],
                               "train", lambda a: load_config(a.config))
    assert (cfg.flow.from_present, cfg.flow.per_frame_t) == (0.1, True)
    saved = json.loads(json.dumps(dataclasses.asdict(cfg)))
    assert config_from_dict(saved).flow == cfg.flow
    for k in ("from_present", "per_frame_t"):
        del saved["flow"][k]
    assert (config_from_dict(saved).flow.from_present, config_from_dict(saved).flow.per_frame_t) == (0.0, False)


def _random_batch(cfg, seed=0):
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


@pytest.mark.parametrize("lever", [dict(from_present=0.1), dict(per_frame_t=True), dict(moving_weight=4.0)])
def test_a_few_train_steps_with_a_lever_on_are_finite_and_learn(lever):
    cfg = Config(model=ModelConfig(**SMALL), data=DataConfig(image_size=(8, 8), context_frames=K, future_frames=T,
                                                               batch_size=8),
                 flow=FlowConfig(**lever), train=TrainConfig(lr=1e-3, warmup_steps=1, steps=20, progress=False,
                                                             tensorboard=False, async_checkpointing=False))
    step = jax.jit(train.make_train_step(cfg))
    state, batch, losses = train.init_state(cfg), _random_batch(cfg), []
    for _ in range(8):
        state, metrics = step(state, batch)
        losses.append(float(metrics["loss"]))
    assert np.all(np.isfinite(losses)), losses
    assert min(losses[-3:]) < losses[0], losses


def test_a_distillation_teacher_must_flow_from_the_students_source(tmp_path):
    """Teacher and student sample from one source: a teacher saved with another flow.from_present is a one-line
    error before training, and flow.distill_loss refuses the mismatch."""
    from sc3_jax.train import distill
    from sc3_jax.core.errors import UserError
    teacher = Config(model=ModelConfig(**SMALL), flow=FlowConfig(from_present=0.1))
    (tmp_path / "teacher").mkdir()
    (tmp_path / "teacher" / "config.json").write_text(json.dumps(dataclasses.asdict(teacher)))
    student = dataclasses.replace(teacher, flow=FlowConfig(distill_teacher=str(tmp_path / "teacher")),
                                  train=TrainConfig(init_from=str(tmp_path / "teacher")))
    with pytest.raises(UserError, match="from.present"):
        distill.teacher_config(student)
    fcfg = dataclasses.replace(student.flow, from_present=0.1)
    assert distill.teacher_config(dataclasses.replace(student, flow=fcfg)).flow.from_present == 0.1
    video, actions, stride = _tokens(2)
    with pytest.raises(ValueError, match="from_present"):
        flow.distill_loss(None, None, MCFG, video, actions, stride, jax.random.key(0), PROBS, GRID, fcfg,
                          teacher_fcfg=FlowConfig())
