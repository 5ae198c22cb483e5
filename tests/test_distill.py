"""Progressive distillation of the sampler (flow.distill_teacher): a student started from the teacher learns to
produce in one Euler step what the teacher produces in two, from the same noise and conditions; off, training is
exactly what it was. The teacher in these tests is a random model with perturbed (non-zero) output heads: an
untrained residual model's samples are its anchor whatever the step count, so there would be nothing to distil."""
import dataclasses
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.model import checkpoint, flow, modes, sharding
from sc3_jax.train import distill, train
from sc3_jax.core.config import Config, FlowConfig, MeshConfig, load_config, replace
from sc3_jax.data import pipeline, synthetic
from sc3_jax.data.episodes import EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.core.errors import UserError
from sc3_jax.model import dit
from sc3_jax.model.tokenizer import context_token_frames, make_tokenizer, token_geometry

from _training_checks import assert_resumed_like_straight, assert_same_training

PROBS = (0.6, 0.1, 0.3)  # every mode in a batch of 8 (tiny's mixture)
STEPS = 40


def tiny(tmp_path, **flow_fields) -> Config:
    """The tiny recipe (shortcuts, residual prediction, t biased high) at a smaller width, with the shipped model's
    pose conditioning and context noise (training and inference levels), so the sampler's whole path is
    distilled."""
    cfg = load_config("tiny")
    return replace(cfg, model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                   rope_axes_dim=(2, 3, 3), pose_conditioning=True, context_noise=True),
                   data=dict(path=str(tmp_path / "episodes"), batch_size=8, future_frames=3),
                   modes=dict(probs=PROBS), flow=dict(context_noise_max=0.3, **flow_fields),
                   sample=dict(context_noise=0.02), mesh=MeshConfig(1, 1, 1),
                   train=dict(workdir=str(tmp_path / "student"), lr=1e-3, warmup_steps=1, log_every=1,
                              ckpt_every=1000, progress=False, tensorboard=False, async_checkpointing=False))


def perturbed(cfg: Config, seed: int = 0) -> dict:
    token_dim, grid = token_geometry(cfg)

    @jax.jit  # one compile, not one dispatch per op
    def init():
        p = dit.init_params(cfg.model, token_dim, jax.random.key(seed), grid)
        return jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(seed + 1), x.shape), p)
    return init()


def noise_params(cfg: Config, seed: int = 0) -> dict:
    """Params of the right shapes, N(0, 0.05) everywhere, with no compile (for the checks that never sample)."""
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda s: rng.normal(0, 0.05, s.shape).astype(s.dtype), checkpoint.param_shapes(cfg))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """(tmp dir, config, saved teacher dir) without data: random params and unit norm stats."""
    tmp = tmp_path_factory.mktemp("distill_saved")
    cfg = tiny(tmp)
    return tmp, cfg, checkpoint.save(tmp / "teacher", cfg, NormStats(np.zeros(7), np.ones(7)), noise_params(cfg),
                                     np.float32)


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """(tmp dir, config, saved teacher dir): synthetic episodes and a teacher exported with their norm stats."""
    tmp = tmp_path_factory.mktemp("distill")
    synthetic.generate(tmp / "episodes", 4, length=30, image_size=(16, 16), seed=0, progress=False)
    cfg = tiny(tmp)
    stats = NormStats.from_store(EpisodeStore(tmp / "episodes"))
    path = checkpoint.save(tmp / "teacher", cfg, stats, jax.device_get(perturbed(cfg)), np.float32)
    return tmp, cfg, path


def _tokens(cfg: Config, B: int, seed: int):
    ks = jax.random.split(jax.random.key(seed), 3)
    K, T = cfg.data.context_frames, cfg.data.future_frames
    token_dim, grid = token_geometry(cfg)
    n = grid[0] * grid[1]
    return (jax.random.normal(ks[0], (B, 3, K + T, n, token_dim)), jax.random.normal(ks[1], (B, T, 7)),
            jax.random.normal(ks[2], (B, T + 1, 7)), grid)


def test_loss_is_zero_for_the_teacher_itself_at_one_step_and_positive_at_two(tmp_path):
    """Student == teacher: at distill_steps 1 the loss and its teacher baseline are exactly 0; at 2 the
    loss equals the teacher's own 1-step baseline and is positive, the student's gradient (through a 1-step
    flow.sample) is not 0 and the teacher's is (it is a frozen target)."""
    cfg = tiny(tmp_path)
    params = noise_params(cfg)
    video, actions, pose, grid = _tokens(cfg, 8, 2)
    stride = jnp.ones((8,), jnp.int32)

    @jax.jit
    def both(student, teacher):
        def loss(s, t, steps):
            return flow.distill_loss(s, t, cfg.model, video, actions, stride, jax.random.key(3), PROBS, grid,
                                     replace(cfg.flow, distill_steps=steps), pose=pose, context_noise=0.02)
        return loss(student, teacher, 1), jax.value_and_grad(lambda s, t: loss(s, t, 2), argnums=(0, 1),
                                                             has_aux=True)(student, teacher)

    (l1, m1), ((l2, m2), (g2, gt2)) = both(params, params)
    norm = lambda g: max(float(jnp.abs(x).max()) for x in jax.tree.leaves(g))  # noqa: E731
    assert float(l1) == 0.0 and float(m1["loss_teacher_1step"]) == 0.0
    assert float(l2) > 1e-6 and float(l2) == float(m2["loss_teacher_1step"])
    assert float(m2["frac_forward"]) > 0 and float(m2["loss_forward"]) > 0
    assert norm(g2) > 1e-6 and norm(gt2) == 0.0


@pytest.mark.slow  # a distillation run and a sampler compile, ~17 s: the default run stays under 30 s
def test_distilled_student_samples_closer_to_the_teacher_on_held_out_windows(teacher):
    """40 distillation steps through `sc3 train`'s loop: the loss falls below the teacher's own 1-step loss, and on
    windows of held-out episodes (new noise) the student's 1-step sample is at least twice closer to the teacher's
    2-step sample than the teacher's own 1-step sample is (measured: ~4.7x)."""
    tmp, cfg, path = teacher
    cfg = replace(cfg, flow=dict(distill_teacher=str(path)), train=dict(init_from=str(path), steps=STEPS))
    train.train(cfg, sharding.make_mesh(cfg.mesh, jax.devices()[:1]))
    rows = train.read_metrics(cfg.train.workdir)
    assert rows[1]["loss"] == pytest.approx(rows[1]["loss_teacher_1step"], rel=1e-5)  # starts as the teacher
    late = [rows[s] for s in range(STEPS - 9, STEPS + 1)]
    assert np.mean([r["loss"] for r in late]) < 0.5 * np.mean([r["loss_teacher_1step"] for r in late])

    synthetic.generate(tmp / "held_out", 2, length=30, image_size=(16, 16), seed=1, progress=False)
    _, stats, t_params = checkpoint.load(path)
    _, _, s_params = checkpoint.load(cfg.train.workdir)
    data = replace(cfg, data=dict(path=str(tmp / "held_out"), batch_size=16, seed=5)).data
    batch = next(pipeline.make_iterator(data, EpisodeStore(tmp / "held_out"), stats))
    tok = make_tokenizer(cfg.model)
    grid = tok.grid(cfg.data.image_size)

    @jax.jit
    def errors(t_params, s_params, frames, actions, stride, pose):
        video = tok.encode(frames)
        B, V, F = video.shape[:3]
        K = F - actions.shape[1]
        vn, an = modes.fixed(modes.FD, B, V, K, actions.shape[1])

        def fd(p, steps):
            return flow.sample(p, cfg.model, video, actions, stride, vn, an, jax.random.key(100), steps, grid,
                               fcfg=cfg.flow, pose=pose, context_noise=cfg.sample.context_noise)[0][:, :, K:]
        target = fd(t_params, 2)
        return jnp.mean(jnp.square(fd(t_params, 1) - target)), jnp.mean(jnp.square(fd(s_params, 1) - target))

    teacher_1, student_1 = (float(x) for x in errors(t_params, s_params, batch["frames"], batch["actions"],
                                                     batch["stride"], batch["pose"]))
    print(f"held-out MSE to the teacher's 2-step sample: teacher 1 step {teacher_1:.5f}, student {student_1:.5f}")
    assert teacher_1 > 1e-4, "the teacher's 1 and 2 steps agree: nothing to distil, the test proves nothing"
    assert student_1 < 0.5 * teacher_1, (student_1, teacher_1)


def test_a_teacher_of_another_model_config_is_a_one_line_error(saved, tmp_path):
    tmp, cfg, path = saved
    on = replace(cfg, flow=dict(distill_teacher=str(path)), train=dict(init_from=str(path)))
    assert distill.teacher_config(on).model == on.model  # the same config passes (run fields from the student)

    def saved(name, model):  # the checks read the teacher's config.json only, before any params
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(json.dumps(dataclasses.asdict(replace(cfg, model=model))))
        return tmp_path / name

    with pytest.raises(UserError, match=r"model\.dim is 64, this run's 32") as e:
        train.make_train_step(replace(on, flow=dict(distill_teacher=str(saved("wide", dict(dim=64))))))
    assert "\n" not in str(e.value)
    # run fields may differ: the teacher keeps its compute dtype
    bf16 = saved("bf16", dict(dtype="bfloat16", remat="block"))
    t = distill.teacher_config(replace(on, flow=dict(distill_teacher=str(bf16))))
    assert t.model == replace(on.model, dtype="bfloat16")
    for bad, match in ((dict(flow=dict(distill_teacher=str(tmp_path / "none"))), "no config.json"),
                       (dict(train=dict(init_from=None)), "--train.init-from"),
                       (dict(flow=dict(distill_steps=0)), "distill_steps"),
                       (dict(flow=dict(self_forcing=0.5)), "self-forcing")):
        with pytest.raises(UserError, match=match) as e:
            distill.teacher_config(replace(on, **bad))
        assert "\n" not in str(e.value)
    other_stats = NormStats(np.zeros(7), np.full(7, 2.0))
    with pytest.raises(UserError, match="action normalisation"):
        distill.check_teacher_stats(on, other_stats)
    distill.check_teacher_stats(on, checkpoint.read_norm_stats(path))


def test_teacher_is_placed_like_the_student_and_kept_out_of_the_state(saved):
    """On 8 devices (data 2 x fsdp 4): every teacher leaf has its student leaf's sharding and the teacher's values;
    the train state (what checkpoints hold) has no teacher in it."""
    tmp, cfg, path = saved
    cfg = replace(cfg, flow=dict(distill_teacher=str(path)), train=dict(init_from=str(path)),
                  mesh=MeshConfig(2, 4, 1))
    mesh = sharding.make_mesh(cfg.mesh)
    abstract, st_shard = train.state_shardings(cfg, mesh)
    assert set(abstract) == {"params", "opt_state", "step", "rng"}
    loaded = distill.load_teacher(cfg, st_shard["params"])
    want = checkpoint.load(path)[2]
    sharded = 0
    for x, s, w in zip(jax.tree.leaves(loaded), jax.tree.leaves(st_shard["params"]), jax.tree.leaves(want)):
        assert x.sharding == s
        sharded += not s.is_fully_replicated
        np.testing.assert_array_equal(np.asarray(x), np.asarray(w))
    assert sharded, "every leaf replicated: the placement is not checked"


def _step_before_distillation(cfg: Config):
    """train.make_train_step as it was before distillation existed (verbatim, one micro-batch): the reference the
    off switch must equal."""
    tok = make_tokenizer(cfg.model)
    grid = tok.grid(cfg.data.image_size)
    opt = train.make_optimizer(cfg)
    K_tok = context_token_frames(cfg)
    shift = train.self_forcing_shift(cfg)

    def grads_and_metrics(params, batch, rng):
        video = tok.from_latents(batch["latents"]) if "latents" in batch else tok.encode(batch["frames"])
        loss_fn = lambda p: flow.loss(p, cfg.model, video, batch["actions"], batch["stride"], rng,  # noqa: E731
                                      cfg.modes.probs, grid, cfg.flow, context_frames=K_tok,
                                      pose=batch.get("pose"), self_forcing_shift=shift)
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        return grads, metrics

    def train_step(state, batch):
        import optax
        rng = jax.random.fold_in(jax.random.wrap_key_data(state["rng"]), state["step"])
        grads, metrics = grads_and_metrics(state["params"], batch, rng)
        updates, opt_state = opt.update(grads, state["opt_state"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        metrics["grad_norm"] = optax.tree.norm(grads)
        return {**state, "params": params, "opt_state": opt_state, "step": state["step"] + 1}, metrics

    return train_step


def test_off_trains_exactly_as_before(tmp_path):
    """distill_teacher None (the default): two train steps give bit-identical params and metrics (same keys) to the
    step as it was before distillation; the compiled step takes (state, batch) as before."""
    cfg = tiny(tmp_path)
    assert cfg.flow.distill_teacher is FlowConfig().distill_teacher is None
    rng = np.random.default_rng(0)
    batches = []
    for _ in range(2):
        b = {}
        for k, s in train.batch_shapes(cfg).items():
            b[k] = (rng.integers(0, 256, s.shape, dtype=np.uint8) if s.dtype == np.uint8 else
                    rng.integers(1, 3, s.shape).astype(s.dtype) if np.issubdtype(s.dtype, np.integer) else
                    rng.normal(size=s.shape).astype(s.dtype))
        batches.append(b)

    def run(make):
        step = jax.jit(make(cfg))
        state, rows = train.init_state(cfg), []
        for b in batches:
            state, metrics = step(state, b)
            rows.append(jax.device_get(metrics))
        return jax.device_get(state["params"]), rows

    assert_same_training(run(train.make_train_step), run(_step_before_distillation))


@pytest.mark.slow  # three distillation runs (three compiles), ~22 s
def test_resume_is_exact_and_reads_the_teacher_again(teacher, monkeypatch):
    """Two steps, stop, resume to four: every metric of every step equals an uninterrupted run's; the resumed run
    read the teacher from its path again (it is not in the checkpoint); a resume that changes the teacher or the
    inference context noise it distils at is refused."""
    tmp, cfg, path = teacher

    def cfg_for(name):
        return replace(cfg, flow=dict(distill_teacher=str(path)),
                       train=dict(init_from=str(path), workdir=str(tmp / name), steps=4, ckpt_every=2))

    loads = []
    real = distill.load_teacher
    # patched where the train loop calls it
    monkeypatch.setattr(train, "load_teacher", lambda *a, **k: loads.append(1) or real(*a, **k))
    mesh = sharding.make_mesh(cfg.mesh, jax.devices()[:1])
    train.train(cfg_for("straight"), mesh)
    train.train(cfg_for("resumed"), mesh, stop_at=2)
    assert sorted(train.read_metrics(tmp / "resumed")) == [1, 2]
    train.train(cfg_for("resumed"), mesh)
    assert len(loads) == 3
    assert_resumed_like_straight(tmp / "straight", tmp / "resumed", "loss_teacher_1step")
    saved = json.loads((tmp / "resumed" / "config.json").read_text())
    assert saved["flow"]["distill_teacher"] == str(path)
    with pytest.raises(UserError, match="sample.context_noise"):
        train.check_workdir(replace(cfg_for("resumed"), sample=dict(context_noise=0.05)))
    with pytest.raises(UserError, match="flow.distill_teacher"):
        train.check_workdir(replace(cfg_for("resumed"), flow=dict(distill_teacher=str(tmp / "elsewhere"))))
    train.check_workdir(replace(cfg_for("resumed"), sample=dict(steps=3)))  # other sampler settings may change


def test_a_student_sampled_at_other_than_1_step_is_warned_about():
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig
    from sc3_jax.evaluation.world_model_defaults import evaluation_config, warn_if_student_off_its_step

    student = replace(load_config("tiny"), flow=dict(distill_teacher="teacher/"))
    with pytest.warns(UserWarning, match="trained for 1"):
        warn_if_student_off_its_step(evaluation_config(student, SweepConfig()))  # the default 2 steps
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_student_off_its_step(evaluation_config(student, SweepConfig(sample_steps=1)))
        warn_if_student_off_its_step(replace(evaluation_config(student, SweepConfig()), sample=dict(steps=1)))
        warn_if_student_off_its_step(evaluation_config(load_config("tiny"), SweepConfig()))  # not a student


def test_a_distilled_run_is_costed_before_it_starts_at_its_own_depth(tmp_path):
    from sc3_jax.train import flops, sizing

    cfg = tiny(tmp_path)
    deep = replace(cfg, model=dict(depth=3))
    path = checkpoint.save(tmp_path / "teacher", deep, NormStats(np.zeros(7), np.ones(7)), noise_params(deep),
                           np.float32)
    on = replace(deep, flow=dict(distill_teacher=str(path)), train=dict(init_from=str(path)))
    # lowered at 1 and 2 layers and extrapolated (sc3 train's cost line): the teacher's passes counted, its params
    # never read, and the same count as the whole step lowered at its own depth
    assert sizing.step_flops(on) == pytest.approx(flops.train_step_flops(on), rel=1e-5)
    assert sizing.step_flops(on) > 1.5 * sizing.step_flops(replace(deep, train=dict(init_from=str(path))))
    with pytest.raises(UserError, match=r"model\.depth is 3, this run's 2"):
        sizing.step_flops(replace(on, model=dict(depth=2)))
