"""Training: state, the sharded train step, orbax checkpoints with the data position, metrics, and the loop.
Reads top to bottom: state -> step -> checkpoints -> metrics -> loop."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp

from sc3_jax.core import atomic, locks
from sc3_jax.model import checkpoint, flow, sharding
from sc3_jax.train import lineage
from sc3_jax.train.distill import WithTeacher, check_teacher_stats, load_teacher, teacher_config
from sc3_jax.core.config import Config, config_from_dict
from sc3_jax.core.errors import UserError
from sc3_jax.model import dit
from sc3_jax.model.tokenizer import context_token_frames, make_tokenizer, token_geometry
from sc3_jax.core.validate import check_host_memory


# ================================================================================================================
# State
# ================================================================================================================
def warmup_of(t) -> int:
    """The run's warm-up steps: ``train.warmup_steps``, or (None) a thirtieth of the run, at most 100 (none under 30
    steps: a smoke run of 1 step still updates); a WSD run's, 100."""
    if t.warmup_steps is not None:
        return int(t.warmup_steps)
    return WSD_WARMUP if t.schedule == "wsd" else min(100, t.steps // 30)


WSD_WARMUP = 100  # a WSD run's default warm-up: fixed, not a share of train.steps (which grows as a trunk goes on)


def lr_schedule(t) -> optax.Schedule:
    """``train.schedule`` "cosine": linear warm-up from 0 to ``t.lr``, then a cosine to 0 *at* ``t.steps``, whatever
    the warm-up: the last steps are where a short run gains most, so none ends mid-decay (``decay_steps <= warmup + 1``
    in optax's schedule rises for the whole run and never decays -- a run must be longer than its warm-up,
    ``check_schedule``). "wsd": :func:`wsd_schedule`."""
    check_schedule(t)
    if t.schedule == "wsd":
        return wsd_schedule(t.lr, warmup_of(t), t.decay_start, t.steps)
    return optax.warmup_cosine_decay_schedule(0.0, t.lr, warmup_of(t), t.steps, end_value=0.0)


def wsd_schedule(peak: float, warmup: int, decay_start: int | None, end: int) -> optax.Schedule:
    """Warm-up / stable / decay (Haegele et al. 2024): linear warm-up to ``peak`` over ``warmup`` steps, then the peak
    held; with ``decay_start`` the rate falls from there to 0 at ``end`` as 1 - sqrt of the decay's progress (their
    best cooldown). Held, the schedule does not depend on ``end``: a trunk resumed with more steps draws the same
    rates, which is what lets it run for weeks and be branched at any step."""
    def rate(step):
        step = jnp.asarray(step, jnp.float32)
        warm = peak * jnp.minimum(1.0, step / warmup) if warmup > 0 else jnp.float32(peak)
        if decay_start is None:
            return warm
        progress = jnp.clip((step - decay_start) / max(1, end - decay_start), 0.0, 1.0)
        return warm * (1.0 - jnp.sqrt(progress))
    return rate


SCHEDULES = ("cosine", "wsd")


def check_schedule(t) -> None:
    """One line for a schedule that cannot run: a warm-up that would swallow a cosine run (the rate would rise until
    the last step), an unknown schedule, a WSD run without a peak to hold, a decay outside the run."""
    if t.schedule not in SCHEDULES:
        raise UserError(f"train.schedule {t.schedule!r}: expected one of {', '.join(SCHEDULES)}")
    warmup = warmup_of(t)
    if t.schedule == "wsd":
        if not (isinstance(t.lr, (int, float)) and 0 < t.lr < float("inf")):
            raise UserError(f"train.schedule wsd holds a peak rate: train.lr {t.lr!r} must be a number > 0")
        if t.decay_start is not None and not warmup <= t.decay_start <= t.steps:
            raise UserError(f"train.decay_start {t.decay_start} must lie between the warm-up's end ({warmup}) and "
                            f"train.steps ({t.steps}): the decay runs from there to 0 at train.steps")
        return
    if t.decay_start is not None:
        raise UserError("train.decay_start is the decay of a WSD run: add --train.schedule wsd, or drop it")
    if warmup >= t.steps:
        raise UserError(f"train.warmup_steps {warmup} >= train.steps {t.steps}: the learning rate would rise for the "
                        f"whole run and never decay; use fewer warm-up steps (e.g. --train.warmup-steps "
                        f"{max(1, t.steps // 30)}) or more steps")


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
    """AdamW (paper defaults) with ``train.schedule``'s rates, global-norm clipping; weight decay on weight
    matrices only (``dit.decay_mask``: not on norms, biases or embeddings, whatever their stacking)."""
    t = cfg.train
    schedule = lr_schedule(t)
    decay = dit.decay_mask(cfg.model, *token_geometry(cfg))
    return optax.chain(optax.clip_by_global_norm(t.grad_clip),
                       optax.adamw(schedule, b1=t.b1, b2=t.b2, weight_decay=t.weight_decay, mask=decay))


def init_state(cfg: Config) -> dict[str, Any]:
    """{params, opt_state, step, rng}; rng is raw key data so checkpoints hold plain arrays."""
    k_init, k_train = jax.random.split(jax.random.key(cfg.train.seed))
    token_dim, grid = token_geometry(cfg)
    params = dit.init_params(cfg.model, token_dim, k_init, grid)
    return {"params": params, "opt_state": make_optimizer(cfg).init(params), "step": jnp.zeros((), jnp.int32),
            "rng": jax.random.key_data(k_train)}


def state_axes(cfg: Config, abstract_state) -> list[tuple]:
    """Logical axes of every state leaf (in ``jax.tree.leaves`` order): optimizer moments follow their parameters
    (matched by the parameter's path at the end of theirs), everything else is replicated."""
    is_axes = lambda a: type(a) is tuple  # noqa: E731  (optax states are namedtuples: containers, not axes)
    flat, _ = jax.tree_util.tree_flatten_with_path(dit.param_axes(cfg.model, *token_geometry(cfg)), is_leaf=is_axes)
    table = {tuple(k.key for k in path): axes for path, axes in flat}

    def axes_for(path, x):
        keys = tuple(getattr(k, "key", None) for k in path)
        for i in range(len(keys)):
            axes = table.get(keys[i:])
            if axes is not None and len(axes) == x.ndim:
                return axes
        return (None,) * x.ndim

    return [axes_for(path, x) for path, x in jax.tree_util.tree_flatten_with_path(abstract_state)[0]]


def state_shardings(cfg: Config, mesh):
    abstract = jax.eval_shape(lambda: init_state(cfg))
    leaves, treedef = jax.tree.flatten(abstract)
    shards = [sharding.named(mesh, axes, x.shape) for axes, x in zip(state_axes(cfg, abstract), leaves)]
    return abstract, jax.tree.unflatten(treedef, shards)


# ================================================================================================================
# Step
# ================================================================================================================
def self_forcing_shift(cfg: Config) -> int:
    """Frames every training window is extended by for ``flow.self_forcing``: l = rollout.keep_frames (a picked
    sample trains on the rollout's next chunk, ``flow.self_forced_window``); 0 when it is off."""
    f = cfg.flow.self_forcing
    if not 0.0 <= f <= 1.0:
        raise UserError(f"flow.self_forcing = {f}: a fraction of forward-dynamics samples, in [0, 1]")
    if f == 0:
        return 0
    if context_token_frames(cfg) is not None:
        raise UserError(f"flow.self_forcing = {f} needs one token frame per frame (tokenizer 'pixel' or 'conv_ae', "
                        f"not {cfg.model.tokenizer!r}): set it to 0")
    if not 1 <= cfg.rollout.keep_frames <= cfg.data.future_frames:
        raise UserError(f"flow.self_forcing shifts windows by rollout.keep_frames = {cfg.rollout.keep_frames}: "
                        f"set it in [1, data.future_frames = {cfg.data.future_frames}]")
    return cfg.rollout.keep_frames


def window_data(cfg: Config):
    """The data config the pipeline reads windows with: ``cfg.data``, with self-forcing's extra frames (actions,
    poses) after the future frames."""
    shift = self_forcing_shift(cfg)
    return dataclasses.replace(cfg.data, future_frames=cfg.data.future_frames + shift) if shift else cfg.data


def make_train_step(cfg: Config, check_teacher: bool = True):
    """One optimizer step. dtype policy (as MaxText's weight_dtype/dtype): params, gradients and Adam moments are
    float32 -- the master weights -- and ``model.dtype`` (e.g. bfloat16) is the compute dtype every matmul casts
    its weights and activations to; norms' variances, attention softmax and the loss stay float32."""
    if jnp.dtype(cfg.model.param_dtype) != jnp.float32:
        raise ValueError(f"model.param_dtype = {cfg.model.param_dtype}: train with float32 params (the master "
                         "weights) and set model.dtype = 'bfloat16' for bf16 compute; bf16 is a storage format "
                         "(sc3 convert --dtype bfloat16, exported models), and init_from casts it back")
    if len(cfg.data.views) == 1 and cfg.modes.probs[1] > 0:
        raise ValueError("cross-view inpainting needs two or more views: set modes.probs[1] = 0 for one view")
    if cfg.model.text_pathway and not cfg.model.prompt_ids:
        raise NotImplementedError("a text_pathway model trains on one fixed prompt: set model.prompt_ids (its token "
                                  "ids from the checkpoint's tokenizer); per-episode prompts are not wired yet -- "
                                  "see docs/cosmos3.md")
    tok = make_tokenizer(cfg.model)
    grid = tok.grid(cfg.data.image_size)
    opt = make_optimizer(cfg)
    K_tok = context_token_frames(cfg)
    shift = self_forcing_shift(cfg)
    teacher_cfg = teacher_config(cfg, check_teacher)
    if cfg.data.anchor and (K_tok is not None or teacher_cfg is not None):
        raise UserError("data.anchor needs one token frame per frame (tokenizer 'pixel' or 'conv_ae') and is not "
                        "wired into distillation yet: set data.anchor False")

    A, B = cfg.train.grad_accum, cfg.data.batch_size
    if A < 1 or B % A:
        raise ValueError(f"train.grad_accum = {A} must be >= 1 and divide data.batch_size = {B}")

    def grads_and_metrics(params, batch, rng, teacher=None):
        video = tok.from_latents(batch["latents"]) if "latents" in batch else tok.encode(batch["frames"])
        loss_fn = lambda p: flow.loss(p, cfg.model, video, batch["actions"], batch["stride"], rng,  # noqa: E731
                                      cfg.modes.probs, grid, cfg.flow, context_frames=K_tok,
                                      pose=batch.get("pose"), self_forcing_shift=shift,
                                      anchor_gap=batch.get("anchor_gap"))
        if teacher_cfg is not None:  # the teacher is an argument, not differentiated: it costs forward passes only
            loss_fn = lambda p: flow.distill_loss(  # noqa: E731
                p, teacher, cfg.model, video, batch["actions"], batch["stride"], rng, cfg.modes.probs, grid,
                cfg.flow, teacher_cfg.model, teacher_cfg.flow, context_frames=K_tok, pose=batch.get("pose"),
                context_noise=cfg.sample.context_noise)
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        return grads, metrics

    def accumulated(params, batch, rng, teacher=None):
        """Mean of the micro-batches' gradients and metrics (the loss is a per-sample mean, so this is the big
        batch's gradient). Micro-batch i takes samples i, i + A, ...: every device keeps its share of each one."""
        micro = jax.tree.map(lambda x: x.reshape(B // A, A, *x.shape[1:]).swapaxes(0, 1), batch)

        def body(acc, i):
            out = grads_and_metrics(params, jax.tree.map(lambda x: x[i], micro), jax.random.fold_in(rng, i), teacher)
            return jax.tree.map(lambda a, o: a + o.astype(a.dtype) / A, acc, out), None

        shapes = jax.eval_shape(grads_and_metrics, params, jax.tree.map(lambda x: x[0], micro), rng, teacher)
        zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, jnp.float32 if s.dtype == jnp.bfloat16 else s.dtype), shapes)
        return jax.lax.scan(body, zeros, jnp.arange(A))[0]

    def train_step(state, batch, teacher=None):
        """``teacher``: the distillation teacher's params (``flow.distill_teacher``; ``load_teacher``)."""
        rng = jax.random.fold_in(jax.random.wrap_key_data(state["rng"]), state["step"])
        grads, metrics = (grads_and_metrics if A == 1 else accumulated)(state["params"], batch, rng, teacher)
        updates, opt_state = opt.update(grads, state["opt_state"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        metrics["grad_norm"] = optax.tree.norm(grads)
        return {**state, "params": params, "opt_state": opt_state, "step": state["step"] + 1}, metrics

    return train_step


def uses_latent_cache(cfg: Config) -> bool:
    """Training reads cached latents (data/latent_cache.py) instead of encoding frames in the step: the learned
    autoencoder (whose encoder would cost more than the model)."""
    return cfg.model.tokenizer == "conv_ae"


def batch_shapes(cfg: Config) -> dict[str, jax.ShapeDtypeStruct]:
    d = window_data(cfg)
    B, V, F = d.batch_size, len(d.views), int(d.anchor) + d.context_frames + d.future_frames
    shapes = {"actions": jax.ShapeDtypeStruct((B, d.future_frames, cfg.model.action_dim), jnp.float32),
              "stride": jax.ShapeDtypeStruct((B,), jnp.int32)}
    if d.anchor:  # data frames between the anchor (the episode's first frame) and the first context frame
        shapes["anchor_gap"] = jax.ShapeDtypeStruct((B,), jnp.int32)
    if uses_latent_cache(cfg):
        tok = make_tokenizer(cfg.model)
        h, w = tok.latent_size(d.image_size)
        shapes["latents"] = jax.ShapeDtypeStruct((B, V, F, h, w, tok.cfg.latent_channels), jnp.float16)
    else:
        shapes["frames"] = jax.ShapeDtypeStruct((B, V, F, *d.image_size, 3), jnp.uint8)
    if cfg.model.pose_conditioning:
        shapes["pose"] = jax.ShapeDtypeStruct((B, d.future_frames + 1, cfg.model.action_dim), jnp.float32)
    return shapes


def compile_train_step(cfg: Config, mesh):
    """jit with explicit shardings and the state donated. Returns (step_fn, state_shardings). With
    ``flow.distill_teacher`` the teacher's params are read here, placed as the student's, and passed to every call
    of step_fn(state, batch) (``WithTeacher``)."""
    _, st_shard = state_shardings(cfg, mesh)
    b_shard = {k: sharding.batch_sharding(mesh) for k in batch_shapes(cfg)}
    if cfg.flow.distill_teacher:
        step = jax.jit(make_train_step(cfg), in_shardings=(st_shard, b_shard, st_shard["params"]),
                       out_shardings=(st_shard, sharding.replicated(mesh)), donate_argnums=(0,))
        return WithTeacher(sharding.bind_mesh(step, mesh), load_teacher(cfg, st_shard["params"])), st_shard
    step = jax.jit(make_train_step(cfg), in_shardings=(st_shard, b_shard),
                   out_shardings=(st_shard, sharding.replicated(mesh)), donate_argnums=(0,))
    return sharding.bind_mesh(step, mesh), st_shard


def create_state(cfg: Config, mesh):
    """A fresh state; with ``cfg.train.init_from`` its params come from there (fresh optimizer, step 0)."""
    _, st_shard = state_shardings(cfg, mesh)
    if not cfg.train.init_from:
        return jax.jit(lambda: init_state(cfg), out_shardings=st_shard)()
    params = checkpoint.load_init_from(cfg, st_shard["params"])  # read straight into their shards

    def fresh(params):
        state = init_state(cfg)  # the random init is dead code under jit: only its optimizer/rng are kept
        return {**state, "params": params, "opt_state": make_optimizer(cfg).init(params)}
    return jax.jit(fresh, in_shardings=(st_shard["params"],), out_shardings=st_shard, donate_argnums=(0,))(params)


# ================================================================================================================
# Train-state checkpoints (resuming: optimizer state and data position; checkpoint.py reads a model's params)
# ================================================================================================================
def checkpoint_manager(cfg: Config, read_only: bool = False) -> ocp.CheckpointManager:
    """The run's own manager; ``read_only``: a reader's beside a run that may be training (``sc3 trunk save`` /
    ``branch``), which must not touch the checkpoint the run is writing (it only restores)."""
    # cleanup_tmp_directories: a checkpoint a kill left half-written (orbax writes it under a temporary name and
    # renames it when complete, so it is never read) is deleted when the run resumes -- by the run only: a reader
    # that cleaned up deleted a live trunk's checkpoint under it (its async commit then failed and the run died)
    options = ocp.CheckpointManagerOptions(max_to_keep=cfg.train.keep_checkpoints,
                                           save_interval_steps=cfg.train.ckpt_every,
                                           enable_async_checkpointing=cfg.train.async_checkpointing,
                                           cleanup_tmp_directories=not read_only)
    return ocp.CheckpointManager(Path(cfg.train.workdir).absolute() / "checkpoints", options=options)


def save(mngr: ocp.CheckpointManager, step: int, state, data_state: dict, force: bool = False) -> bool:
    """``step`` is passed from the loop (reading it off the device state would block on every step)."""
    return mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   data=ocp.args.JsonSave(data_state)), force=force)


def restore(mngr: ocp.CheckpointManager, cfg: Config, mesh, step: int | None = None):
    """(state, data_state) of the latest (or given) checkpoint, placed with this mesh's shardings."""
    step = mngr.latest_step() if step is None else step
    abstract, st_shard = state_shardings(cfg, mesh)
    target = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract, st_shard)
    out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target),
                                                     data=ocp.args.JsonRestore()))
    return out["state"], out["data"]


# ================================================================================================================
# Metrics
# ================================================================================================================
class MetricsLog:
    """One JSON line per step in ``workdir/metrics.jsonl`` (appended across restarts, each step once) and
    TensorBoard events."""

    def __init__(self, workdir: Path, tensorboard: bool, resumed_at: int | None = None):
        """``resumed_at``: the step of the checkpoint the run starts from (0 fresh; None: keep every row). The rows
        after it were logged by an attempt stopped before its next checkpoint; those steps run again, so their old
        rows are dropped (the file rewritten whole, renamed over the old: a kill here loses nothing) before the new
        ones are appended."""
        self.path = workdir / "metrics.jsonl"
        self.is_primary = jax.process_index() == 0
        self.tb = None
        if self.is_primary:  # a line cut by a kill would be glued to the next one: drop it (its step reruns)
            atomic.drop_cut_line(self.path)
            if resumed_at is not None:
                atomic.drop_rows_after(self.path, resumed_at)
        if tensorboard and self.is_primary:
            from tensorboardX import SummaryWriter
            self.tb = SummaryWriter(str(workdir / "tensorboard"))

    def write(self, rows: list[dict]):
        if not self.is_primary or not rows:
            return
        with open(self.path, "a") as f:
            for row in rows:
                f.write(json.dumps(row) + "\n")
        if self.tb is not None:
            for row in rows:
                for k, v in row.items():
                    if k != "step":
                        self.tb.add_scalar(k, v, row["step"])
            self.tb.flush()

    def close(self):
        if self.tb is not None:
            self.tb.close()


def read_metrics(workdir: str | Path) -> dict[int, dict]:
    """step -> row; a step logged twice (a run resumed from an earlier checkpoint) keeps the latest row. A last line
    cut by a kill (or being written) is left out; a damaged one is a one-line ``UserError``."""
    rows = atomic.read_jsonl(Path(workdir) / "metrics.jsonl", "a metrics row",
                             "delete that line (the log is informational: training does not read it)")
    return {row["step"]: row for row in rows}


# ================================================================================================================
# Loop
# ================================================================================================================
def prepare_data(cfg: Config):
    """Episode store, normalisation stats (computed once, stored in the workdir next to the checkpoints) and this
    process's batch iterator (its position is checkpointed)."""
    from sc3_jax.data import pipeline
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.data.norm_stats import NormStats

    workdir = Path(cfg.train.workdir)
    try:
        store = EpisodeStore(cfg.data.path)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{e}. Make a dataset first (`sc3 demo` writes synthetic episodes, `sc3 sim demos "
                                f"--out DIR` simulator demonstrations) and pass --data DIR") from None
    stats_path = workdir / "norm_stats.json"
    src_stats = Path(cfg.train.init_from) / "norm_stats.json" if cfg.train.init_from else None
    if stats_path.exists():
        stats = NormStats.load(stats_path)
    elif cfg.train.resume_from:  # the resumed run's own statistics, as they were
        stats = NormStats.load(Path(cfg.train.resume_from) / "norm_stats.json")
        if jax.process_index() == 0:
            stats.save(stats_path)
    elif src_stats is not None and src_stats.exists():
        # a fine-tuned model must read actions in the units its params learned, not in this dataset's
        stats = reconditioned(NormStats.load(src_stats), store)
        if jax.process_index() == 0:
            stats.save(stats_path)
    else:
        stats = NormStats.from_store(store)
        if jax.process_index() == 0:
            stats.save(stats_path)
    dataset = None
    data = window_data(cfg)  # longer windows with flow.self_forcing
    if uses_latent_cache(cfg):
        from sc3_jax.data import latent_cache
        root = workdir / "latents"
        if jax.process_index() == 0:
            latent_cache.build(store, make_tokenizer(cfg.model), tuple(cfg.data.views), root,
                               progress=cfg.train.progress)
        index = pipeline.build_index(store, data)
        dataset = pipeline.make_dataset(data, store, stats, jax.process_index(), jax.process_count(), index,
                                        latents=latent_cache.LatentReader(root, index.episode_ids))
    it = pipeline.make_iterator(data, store, stats, jax.process_index(), jax.process_count(), dataset)
    return store, stats, it


def reconditioned(src, store):
    """The statistics a fine-tune from ``src`` (a saved model's ``NormStats``) trains with: ``src``'s, unless its pose
    condition is the old displacement from zero (velocities integrated into nothing measured) where this store's
    data say which measured entries the commands move -- then ``src``'s action units with this store's pose
    statistics, mapping and range (the pose input's meaning changes once; the action units stay)."""
    from sc3_jax.data.norm_stats import NormStats

    if src.action_space.kind != "velocity" or src.action_space.measured:
        return src
    new = NormStats.from_store(store)
    if not new.action_space.measured or not src.action_space.same_kind(new.action_space):
        return src
    if jax.process_index() == 0:
        print(f"init_from: the source's pose condition integrated its commands from zero; this run conditions on the "
              f"measured state entries {list(new.action_space.measured)} (gains "
              f"{[round(g, 4) for g in new.action_space.gain]}), the source's action units kept", flush=True)
    return dataclasses.replace(src, pose_mean=new.pose_mean, pose_std=new.pose_std, action_space=new.action_space)


# Fields a resumed run may change: how it runs, logs and checkpoints (and how its model is later sampled), not what
# it learns. train.steps extends (or shortens) a run; the learning-rate schedule follows the new length.
RESUMABLE = ("name", "train.workdir", "train.steps", "train.log_every", "train.ckpt_every", "train.keep_checkpoints",
             "train.async_checkpointing", "train.tensorboard", "train.progress", "data.read_threads", "model.remat",
             "model.attention_impl", "model.attention_block", "mesh.", "sample.", "rollout.")


def check_workdir(cfg: Config) -> None:
    """Refuse, before anything is written, to resume a workdir trained with another config: its checkpoints,
    norm stats and latents belong to the config in its ``config.json``."""
    path = Path(cfg.train.workdir) / "config.json"
    if path.exists():
        diff = config_changes(config_from_dict(atomic.read_json(path, "restore it from a copy")), cfg)
        if diff:
            raise UserError(f"{path.parent} holds a run with another config (changed: {'; '.join(diff)}): resume it "
                            "with its own settings, or use another --train.workdir")
    if cfg.train.resume_from and not path.exists():
        from sc3_jax.train import trunk_state
        src = Path(cfg.train.resume_from)
        trunk_state.read_meta(src)
        diff = config_changes(checkpoint.read_config(src, what="resume_from "), cfg, also=BRANCHABLE)
        if diff:
            raise UserError(f"train.resume_from {src} is a run with another config (changed: {'; '.join(diff)}): "
                            "resume it with its own settings (its config.json)")


# What a run resumed from a travelling state may change besides RESUMABLE: where it starts from, its decay (a
# branch), and the tokenizer's path (a model directory refers to its own copy)
BRANCHABLE = ("train.resume_from", "train.init_from", "train.decay_start", "model.tokenizer_path", "data.path",
              "data.fps", "data.state_dim")


def config_changes(old_cfg: Config, cfg: Config, also: tuple[str, ...] = ()) -> list[str]:
    """The fields ``cfg`` changes from ``old_cfg`` that a resumed run may not change."""
    def flat(d, prefix=""):
        for k, v in d.items():
            yield from flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [(prefix + k, v)]
    # through JSON both ways: tuples and lists compare equal; fields added since the run was written take defaults
    old, new = (dict(flat(json.loads(json.dumps(dataclasses.asdict(c))))) for c in (old_cfg, cfg))
    free = RESUMABLE + also
    return [f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in sorted(old.keys() | new.keys())
            if old.get(k) != new.get(k) and not (k.startswith(free) and not _sets_windows(k, old, new)
                                                 and not _distills_with(k, old, new))]


def _sets_windows(key: str, old: dict, new: dict) -> bool:
    """rollout.keep_frames is what flow.self_forcing shifts (and lengthens) training windows by: then it is
    training data, not a rollout setting, and a resumed run keeps it."""
    return key == "rollout.keep_frames" and bool(old.get("flow.self_forcing") or new.get("flow.self_forcing"))


def _distills_with(key: str, old: dict, new: dict) -> bool:
    """sample.context_noise is the level flow.distill_loss samples teacher and student with: then it is training
    data, not a sampler setting, and a resumed run keeps it."""
    return key == "sample.context_noise" and bool(old.get("flow.distill_teacher") or new.get("flow.distill_teacher"))


def train(cfg: Config, mesh=None, stop_at: int | None = None) -> dict:
    """Train (or resume) until ``cfg.train.steps`` (or ``stop_at``). Returns the last logged metrics.

    One run per workdir: process 0 holds the workdir's lock for the run (``locks``), so a second trainer on it stops
    with a one-line error naming the first. A fresh run writes its config.json after its first step: one that fails
    before it (a config that does not compile, a batch that does not fit) removes what it wrote (norm stats,
    latents), and one killed before it (the kernel's OOM killer) is undone by the next attempt (``INCOMPLETE``), so
    the corrected command is not refused as "another config" and reads no stats of other data."""
    check_schedule(cfg.train)  # a warm-up longer than the run: one line before anything is written
    check_workdir(cfg)
    teacher_config(cfg)  # a wrong teacher is refused before anything is written
    workdir = Path(cfg.train.workdir)
    lead = jax.process_index() == 0
    fresh = not (workdir / "config.json").exists()
    if fresh:
        check_host_memory(cfg)  # a batch the machine cannot hold: one line now, not a silent kill by the kernel
    existed = workdir.exists()
    workdir.mkdir(parents=True, exist_ok=True)
    lock = locks.Lock(workdir, "training run") if lead else None
    started, before = False, None
    try:
        if lead:
            atomic.remove_stale(workdir, recursive=True)  # temporaries of writers killed in an earlier attempt
            if fresh:
                before = _begin_attempt(workdir)
        for last in _steps(cfg, workdir, mesh, stop_at):
            if lead and not started:  # the run exists from its first step: config.json says so; a resume that
                # changed what a resume may (train.steps: the schedule's length) records it, so the file tells
                atomic.write_json(workdir / "config.json", dataclasses.asdict(cfg))
                (workdir / INCOMPLETE).unlink(missing_ok=True)
            started = True
        return last
    except Exception:
        if before is not None and not started:  # a failed start: leave the workdir as it was
            _undo_attempt(workdir, before)
            if not existed and os.listdir(workdir) == [locks.LOCK_NAME]:
                (workdir / locks.LOCK_NAME).unlink()
                workdir.rmdir()
        raise
    finally:
        if lock is not None:
            lock.release()


# A fresh run's workdir before its first step: what was there before the attempt (a kill -9, the kernel's OOM
# killer, leaves it behind; the next attempt removes what the killed one wrote, so the retry is never refused as
# "another config" nor reads the statistics of other data)
INCOMPLETE = "incomplete.json"


def _begin_attempt(workdir: Path) -> set[str]:
    """The names the workdir held before this fresh attempt, after undoing an earlier attempt that was killed."""
    marker = workdir / INCOMPLETE
    if marker.exists():
        try:
            kept = set(atomic.read_json(marker).get("before", []))
        except (UserError, AttributeError):  # the marker itself cut short: keep everything but what it marks
            kept = set(os.listdir(workdir)) - {INCOMPLETE}
        _undo_attempt(workdir, kept)
    before = set(os.listdir(workdir)) - {locks.LOCK_NAME}
    atomic.write_json(marker, {"before": sorted(before)})
    return before


def _undo_attempt(workdir: Path, before: set[str]) -> None:
    """Remove what a failed fresh attempt wrote (config, norm stats, latents, checkpoints, its marker)."""
    for name in set(os.listdir(workdir)) - before - {locks.LOCK_NAME}:
        path = workdir / name
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)


def _steps(cfg: Config, workdir: Path, mesh, stop_at: int | None):
    """The run itself: yields the last logged metrics after each step (and once more at the end)."""
    mesh = sharding.make_mesh(cfg.mesh) if mesh is None else mesh
    _, stats, data_iter = prepare_data(cfg)
    check_teacher_stats(cfg, stats)
    step_fn, _ = compile_train_step(cfg, mesh)
    mngr = checkpoint_manager(cfg)
    if mngr.latest_step() is not None:
        state, data_state = restore(mngr, cfg, mesh)
        data_iter.set_state(data_state["iterator"])
    elif cfg.train.resume_from:
        from sc3_jax.train import trunk_state
        state, data_state = trunk_state.read(cfg.train.resume_from, cfg, *state_shardings(cfg, mesh))
        data_iter.set_state(data_state["iterator"])
    else:
        state = create_state(cfg, mesh)
    start = int(state["step"])
    log = MetricsLog(workdir, cfg.train.tensorboard, resumed_at=start)
    lin = _begin_lineage(cfg, workdir, start)
    _carry_state_head(cfg, workdir)
    clock = lineage.StepClock(time.monotonic())
    stop = _PreemptionFlag()
    end = cfg.train.steps if stop_at is None else min(stop_at, cfg.train.steps)
    pending: list[tuple[int, dict]] = []
    last: dict = {}
    rate_at = lr_schedule(cfg.train)  # logged with every row: the rate each update used, read from the run
    bar = _progress(start, end, cfg.train.progress and jax.process_index() == 0)
    t0, n_since = time.perf_counter(), 0
    for step in range(start, end):
        batch = sharding.global_batch(mesh, _model_batch(next(data_iter), cfg))
        state, metrics = step_fn(state, batch)
        pending.append((step + 1, metrics))
        n_since += 1
        done = step + 1 == end
        preempted = stop.requested() or mngr.reached_preemption(step + 1)
        if len(pending) >= cfg.train.log_every or done or preempted:
            rows = [{"step": s, "lr": float(rate_at(s - 1)), **{k: float(v) for k, v in jax.device_get(m).items()}}
                    for s, m in pending]
            rate = n_since / (time.perf_counter() - t0)
            rows[-1]["steps_per_s"] = rate
            log.write(rows)
            clock.tick(time.monotonic())  # after device_get: the steps since the last tick have run (dispatch is async)
            last, pending, t0, n_since = rows[-1], [], time.perf_counter(), 0
            if bar is not None:
                bar.set_postfix(loss=f"{last['loss']:.4f}", steps_s=f"{rate:.2f}")
        if bar is not None:
            bar.update(1)
        if save(mngr, step + 1, state, {"iterator": data_iter.get_state()}, force=done or preempted):
            lin = lineage.advance(lin, step + 1, clock.wall_s(time.monotonic()), clock.train_s)
            if jax.process_index() == 0:  # the lineage says no more than the checkpoints hold
                atomic.write_json(workdir / lineage.FILE, lin)
        yield last
        if preempted:
            break
    mngr.wait_until_finished()
    mngr.close()
    log.close()
    stop.restore()
    if bar is not None:
        bar.close()
    yield last


def _begin_lineage(cfg: Config, workdir: Path, start: int) -> dict:
    """This stretch's lineage: the workdir's own (a resumed run), else the travelling state's or the init model's it
    continues, else a fresh model's."""
    own = lineage.read(workdir)
    if own is not None:
        return lineage.begin(own, cfg, workdir.name, start)
    src = cfg.train.resume_from or cfg.train.init_from
    return lineage.begin(lineage.read(src), cfg, workdir.name, start, origin=Path(src).name if src else None)


def _carry_state_head(cfg: Config, workdir: Path) -> None:
    """The learned robot state (``rollout/state_head.py``) of the model this run continues, where the run has none
    of its own: it reads the robot's state from real frames and actions, not from the DiT, so it stays valid for the
    continued model (same data, same robot) and its exports keep handing policies the robot's state."""
    src = cfg.train.resume_from or cfg.train.init_from
    head, mine = (Path(src) / "state_head.npz" if src else None), workdir / "state_head.npz"
    if jax.process_index() == 0 and head is not None and head.is_file() and not mine.exists():
        with atomic.replacing(mine) as tmp:
            shutil.copyfile(head, tmp)


def _model_batch(batch: dict, cfg: Config) -> dict:
    return {k: batch[k] for k in batch_shapes(cfg)}


def _progress(start: int, end: int, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm
    return tqdm(total=end, initial=start, desc="train", dynamic_ncols=True)


class _PreemptionFlag:
    """SIGTERM (what schedulers send before preempting) -> save a checkpoint at the next step and stop. With several
    processes the flag is agreed on by all of them (a signal reaching only some hosts must not split the job)."""

    def __init__(self):
        self.flag = False
        try:
            self._old = signal.signal(signal.SIGTERM, self._handler)
        except ValueError:  # not the main thread
            self._old = None

    def _handler(self, *_):
        self.flag = True

    def requested(self) -> bool:
        if jax.process_count() == 1:
            return self.flag
        from jax.experimental import multihost_utils
        return bool(np.any(multihost_utils.process_allgather(np.int32(self.flag))))

    def restore(self):
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)
