"""``sc3 plan``: what a config costs on a mesh of accelerators, without allocating the model.

    sc3 plan --config paper --mesh data=4,fsdp=8 --device gb200 [--mfu 0.4] [--compile] [--batch 256]

Everything starts from abstract shapes (``jax.eval_shape``): nothing of the model is allocated, so a 2B-parameter
config plans on a laptop in seconds.

* Parameters / optimizer: every state leaf's per-device shard shape from the logical-axis rules
  (``sharding.RULES``) on an ``AbstractMesh`` of the requested sizes (no devices needed).
* FLOPs: XLA's cost analysis of the train step of ``train.compile_train_step`` on one device with the layer scan
  unrolled (``scan_layers=False``, as bench/train_step.py counts: the cost analysis counts a loop body once). By
  default the *lowered* (not compiled) module is analysed, which works at any scale; ``--compile`` compiles it and
  reads the compiled module's cost analysis, bench/train_step.py's exact number (the two differ by a few percent
  on tiny configs, < 0.3% at cpu_medium size). The count is global (every sample, every token); per-device numbers
  are the global count divided by the number of devices, i.e. assume a perfect split.
* One rollout chunk (one episode: forward-dynamics sampling of l' frames and inverse-dynamics sampling of their
  actions, S Euler steps each, with context caching as the config does): the lowered cost of the rollout's
  per-chunk model step (``rollout.ChunkFns.model_step``) with S = 1, plus (S - 1) x the cost of one forward and one
  inverse network evaluation (the sampler's ``fori_loop`` body would otherwise be counted once).
* Activations: with ``--compile`` and a mesh that fits on this machine's devices, the compiled train step's
  memory analysis (``temp_size_in_bytes`` per device, the estimate beside it); otherwise an analytic estimate for
  the config's attention kernel and remat policy, printed as such.
* A plan that fits, when the config does not: the memory-efficient attention kernel for the device, the lightest
  remat and the fewest micro-batches whose estimate fits (``fitting_plan``), with its own step FLOPs.
* Times: FLOPs / (devices x peak x MFU). Peaks are approximate vendor dense-BF16 figures per chip (``DEVICES``).
* Shape: views, image size, window, action (= imagined state) dimension and tokenizer all come from the config (a
  store's dataset.json, through ``data.shape.shape_from_dataset``, in ``sc3 plan --data``); ``check_shape``
  refuses, in one line naming the field, a shape the model cannot take, before anything is traced.
* Wan VAE tokenizers: never allocated; their share is counted apart (``plan_vae.py``).
"""
from __future__ import annotations

import dataclasses
import functools
import math

from sc3_jax.core import xla_cost
from sc3_jax.core.errors import UserError
from sc3_jax.train.plan_vae import WAN, shape_only_vae, vae_config, vae_costs, vae_note

# device: (approximate vendor peak dense BF16 FLOP/s per chip, HBM bytes per chip)
DEVICES: dict[str, tuple[float, float]] = {
    "h100": (989e12, 80e9),  # H100 SXM: 989 TFLOP/s dense BF16, 80 GB HBM3
    "h200": (989e12, 141e9),  # H200 SXM: same compute as H100, 141 GB HBM3e
    "gb200": (2.5e15, 186e9),  # one Blackwell GPU of a GB200 NVL72: ~2.5 PFLOP/s dense BF16, ~186 GB HBM3e
    "v5p": (459e12, 95e9),  # TPU v5p chip: 459 TFLOP/s BF16, 95 GB HBM2e
}
MESH_KEYS = ("data", "fsdp", "tensor", "context")


def parse_mesh(text: str):
    """"data=4,fsdp=8[,tensor=1][,context=1]" -> MeshConfig (missing axes = 1)."""
    from sc3_jax.core.config import MeshConfig

    sizes = {k: 1 for k in MESH_KEYS}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        if not sep or key.strip() not in sizes or not value.strip().lstrip("-").isdigit():
            raise UserError(f"--mesh: expected AXIS=SIZE with AXIS in {', '.join(MESH_KEYS)} and SIZE an integer, "
                            f"got {part!r}")
        sizes[key.strip()] = int(value)
    if any(v < 1 for v in sizes.values()):
        raise UserError(f"--mesh: every axis size must be >= 1 (the planner needs explicit sizes), got {text!r}")
    return MeshConfig(**sizes)


OWN_OPTION = {"data.path": "--data", "data.batch_size": "--batch"}  # config field -> its option in sc3 train / plan


def config_flag(key: str, value) -> str:
    """The command-line option that sets config field ``key`` ("section.field") to ``value``, as every command
    spells config overrides (``commands.parse_with_config``): ``--model.attention-impl ring``; the two fields with an
    option of their own in sc3 train and sc3 plan by it (``commands/flags.py`` CONFIG_FIELDS, a test ties the two):
    ``--batch 64``."""
    if key in OWN_OPTION:
        return f"{OWN_OPTION[key]} {value}"
    section, _, field = key.partition(".")
    name = field.replace("_", "-")
    if isinstance(value, bool):
        return f"--{section}.{'' if value else 'no-'}{name}"
    if isinstance(value, (tuple, list)):
        value = " ".join(map(str, value))
    return f"--{section}.{name} {value}"


# ----------------------------------------------------------------------------------------------------------------
# Shape: what the config says the robot and its cameras are, checked before anything is traced
# ----------------------------------------------------------------------------------------------------------------
def check_shape(cfg, chunk: bool = True, *, action_space, data_fps: float | None) -> None:
    """One-line UserError naming the field when the model cannot take the config's shape (views, image size,
    window, action dimension, tokenizer); the library would otherwise fail deep inside a trace. ``chunk``: also the
    rollout's window (rollout.keep_frames, rollout.policy_chunk). ``action_space`` / ``data_fps``: the robot's
    (a store's or a saved model's; None where a config is planned without its data: ``cost_robot``)."""
    d, m = cfg.data, cfg.model
    V = len(d.views)
    if V < 1:
        raise UserError("data.views is empty: name the camera views, e.g. --data.views left right wrist")
    if m.num_views != V:
        raise UserError(f"model.num_views={m.num_views}, but data.views has {V} ({' '.join(d.views)}): set "
                        f"{config_flag('model.num_views', V)} (or --data.views with {m.num_views} names)")
    if m.action_dim < 1:
        raise UserError(f"model.action_dim={m.action_dim}: an action needs at least one dimension")
    if len(d.image_size) != 2 or min(d.image_size) < 1:
        raise UserError(f"data.image_size={list(d.image_size)}: expected HEIGHT WIDTH, both positive")
    for key, n in (("data.context_frames", d.context_frames), ("data.future_frames", d.future_frames),
                   ("data.batch_size", d.batch_size)):
        if n < 1:
            raise UserError(f"{key}={n}: must be >= 1")
    if V == 1 and cfg.modes.probs[1] > 0:
        raise UserError(f"modes.probs={list(cfg.modes.probs)}: cross-view inpainting (the second entry) needs two "
                        "views or more and data.views has one: set it to 0")
    H, W = d.image_size
    if m.tokenizer == "pixel" and (H % m.patch_size or W % m.patch_size):
        raise UserError(f"data.image_size={[H, W]} is not a multiple of model.patch_size={m.patch_size} (pixel "
                        "patches): change either")
    if m.tokenizer == "conv_ae" and not m.tokenizer_path:
        raise UserError("model.tokenizer_path: the conv_ae tokenizer needs one (a `sc3 train-tokenizer` output)")
    if m.tokenizer in WAN:
        vae = vae_config(m)
        r, c = vae.spatial_ratio, vae.temporal_ratio
        if H % r or W % r:
            raise UserError(f"data.image_size={[H, W]} is not a multiple of {r}, the {m.tokenizer} VAE's spatial "
                            "downsampling (model.tokenizer): change data.image_size")
        if (d.context_frames - 1) % c:
            raise UserError(f"data.context_frames={d.context_frames}: the {m.tokenizer} VAE ({c}x time compression) "
                            f"needs 1 + {c} k context frames (e.g. {1 + c})")
        if d.future_frames % c:
            raise UserError(f"data.future_frames={d.future_frames}: the {m.tokenizer} VAE ({c}x time compression) "
                            f"needs a multiple of {c}")
        if m.layout != "cosmos3":
            raise UserError(f"model.layout={m.layout!r}: {c}x time-compressed {m.tokenizer} tokens carry {c} actions "
                            f"per token frame, which only the cosmos3 layout has: set --model.layout cosmos3")
        for field in ("action_to_frames", "action_reads_frames"):  # the small-model shortcuts pair action j with
            if getattr(m, field):  # future frame j
                raise UserError(f"model.{field}: this shortcut needs one action per future token frame; "
                                f"{m.tokenizer} token frames carry {c} actions: {config_flag(f'model.{field}', False)}")
    if chunk:
        from sc3_jax.rollout import rollout

        try:  # its messages name the rollout field (rollout.keep_frames=..., rollout.policy_chunk=...)
            fps, space = cost_robot(cfg, action_space, data_fps)
            rollout.make_spec(cfg, fps, num_chunks=1, action_space=space)
        except ValueError as e:
            raise UserError(f"{e} (or plan without the rollout chunk: --no-chunk)") from None


def cost_robot(cfg, action_space, data_fps: float | None):
    """(data_fps, action_space) as ``rollout.make_spec`` takes them, for costing a chunk: the robot's where
    known (a store's, ``sc3 plan --data``, or the config's ``data.fps``); where not, stand-ins that name no robot --
    absolute targets of the model's dimension and one data frame per rollout frame (stride 1) -- since a chunk's
    cost depends on neither the action kind nor the frame stride."""
    from sc3_jax.data.action_space import ActionSpace

    space = ActionSpace("absolute", cfg.model.action_dim) if action_space is None else action_space
    fps = cfg.rollout.control_hz if data_fps is None else data_fps
    return fps, space


# ----------------------------------------------------------------------------------------------------------------
# Pieces
# ----------------------------------------------------------------------------------------------------------------
def _counting_cfg(cfg):
    """The config whose single-device program XLA can count: layers unrolled, one micro-batch (a loop body is
    counted once; gradient accumulation does not change the FLOPs of a step), dense attention (context-parallel
    attention has the same FLOPs, but inside ``shard_map`` a lowered module holds one device's share)."""
    from sc3_jax.core.config import MeshConfig, replace

    return replace(cfg, model=dict(scan_layers=False, attention_impl="dense"), train=dict(grad_accum=1),
                   mesh=MeshConfig(1, 1, 1))


def train_step_flops(cfg, compiled: bool = False, check_teacher: bool = True) -> float:
    """Global FLOPs of one train step: bench/train_step.py's count (``compiled=True``) or the lowered module's.
    With a Wan VAE tokenizer, the DiT's step on the VAE's tokens (the VAE's encode: ``vae_costs``). A distilled
    step counts its teacher's passes with the teacher's params as shapes (never read); ``check_teacher=False``
    skips the check that the teacher's model config is the student's (``sizing.step_flops`` lowers at one and two
    layers)."""
    import jax

    from sc3_jax.model import sharding
    from sc3_jax.train import train

    c = _counting_cfg(cfg)
    mesh = sharding.make_mesh(c.mesh, jax.devices()[:1])
    with shape_only_vae(c):  # a Wan VAE's encode is not in this count (vae_costs)
        abstract = jax.eval_shape(lambda: train.init_state(c))
        if c.flow.distill_teacher:
            step = sharding.bind_mesh(jax.jit(train.make_train_step(c, check_teacher)), mesh)
            return xla_cost.flops(step.lower(abstract, train.batch_shapes(c), abstract["params"]), compiled)
        step, _ = train.compile_train_step(c, mesh)
        return xla_cost.flops(step.lower(abstract, train.batch_shapes(c)), compiled)


def chunk_programs(cfg, *, action_space, data_fps: float | None, cache: bool = True, policy=None) -> dict:
    """One rollout chunk of one episode as separately traced programs (``jax.stages.Traced``; abstract inputs, so
    nothing is allocated), each run by the rollout as it is written (``rollout.ChunkFns.model_step``):

        "tokenizer encode"   the context frames (every chunk)          "tokenizer decode"  the kept frames
        "context encoding"   the context's keys/values (FD cache)      "forward step"      one FD Euler step
        "inverse encoding"   every frame's keys/values (ID cache)      "inverse step"      one ID Euler step
        "policy"             observe + one call of ``policy``          "model step"        the whole step, S = 1

    ``cache=False``: the uncached sampler (no encodings; every step runs every token). ``policy``: a JaxPolicy
    (None: ``policies.simple.linear_policy``). The loops of the model step (the sampler's, the state integration's)
    run once at S = 1, which is why it is traced there: XLA's cost analysis counts a loop body once."""
    import jax
    import jax.numpy as jnp

    from sc3_jax.model import flow, modes
    from sc3_jax.rollout import rollout
    from sc3_jax.model import dit
    from sc3_jax.policies import simple

    m = cfg.model
    fps, space = cost_robot(cfg, action_space, data_fps)
    spec = rollout.make_spec(cfg, fps, num_chunks=1, action_space=space)
    st = rollout.ChunkFns(m, cfg.flow, dataclasses.replace(spec, steps=1, inverse_steps=1), cache)
    sds = jax.ShapeDtypeStruct
    params = jax.eval_shape(lambda: dit.init_params(m, st.tok.token_dim, jax.random.key(0), st.grid))
    V, K, T, H, W, A, a = spec.views, spec.context, spec.predict, *spec.image_size, spec.action_dim, spec.anchor
    carry = rollout.Carry(sds((V, K, H, W, 3), jnp.float32), sds((A,), jnp.float32), sds((), bool),
                          sds((), jnp.int32), sds((spec.state_dim,), jnp.float32), sds((V, a, H, W, 3), jnp.float32))
    key = jax.eval_shape(lambda: jax.random.key_data(jax.random.key(0)))
    norm = (*(sds((A,), jnp.float32) for _ in range(4)), None)  # NormStats.arrays: action, state mean / std; head
    Kt, Tt = st.window
    Kt += a  # the anchor's token frame sits in front of the context
    P, Dt = jax.eval_shape(st.tok.encode, carry.context).shape[-2:]
    video = sds((1, V, Kt + Tt, P, Dt), jnp.float32)
    pose = sds((1, T + 1, A), jnp.float32) if m.pose_conditioning else None  # what flow.sample hands the model
    level = sds((1,), jnp.float32) if m.context_noise else None
    gap = sds((1,), jnp.int32) if a else None
    jit = lambda f, *args: jax.jit(f).trace(*args)  # noqa: E731
    kept = (Kt, Kt + spec.keep) if st.tok.time_compression == 1 else (0, Kt + Tt)  # what model_step decodes
    progs = {"tokenizer encode": jit(st.tok.encode, sds((V, a + K, H, W, 3), jnp.float32)),
             "tokenizer decode": jit(lambda v: st.tok.decode(v[0][:, slice(*kept)], spec.image_size), video)}
    for mode, prefix, encoding, step in ((modes.FD, "context", "context encoding", "forward step"),
                                         (modes.ID, "video", "inverse encoding", "inverse step")):
        vn, an = jax.eval_shape(lambda mode=mode: modes.fixed(mode, 1, V, Kt, Tt, num_actions=T))
        inp = dit.Inputs(video, sds((1, T, A), jnp.float32), sds((1, V, Kt + Tt), jnp.float32), vn,
                         sds((1, T), jnp.float32), an, sds((1,), jnp.int32), pose=pose, context_level=level,
                         anchor_gap=gap)
        kv = None
        if cache and m.context_attention == "causal":  # as model_step: the inverse sampler extends the context's
            shared = ctx_kv if mode == modes.ID and flow.shares_context(m, spec.context_noise) else None
            encode = functools.partial(dit.encode_context, cfg=m, grid=st.grid, prefix=prefix, context_frames=Kt)
            progs[encoding] = jit(lambda p, i, c: encode(p, inp=i, context_kv=c), params, inp, shared)
            kv = ctx_kv = jax.eval_shape(lambda p, i, c: encode(p, inp=i, context_kv=c), params, inp, shared)
        progs[step] = jit(lambda p, i, c: flow.predict(p, m, i, st.grid, c, Kt), params, inp, kv)
    policy = policy or simple.linear_policy(jax.random.key(0), V, spec.policy_chunk, action_dim=A)

    def act(pp, c, task, k):
        obs, k_pol = st.observe(c, task, k)
        return policy.apply(pp, obs, jax.random.wrap_key_data(k_pol))
    progs["policy"] = jit(act, policy.params, carry, sds((), jnp.int32), key)
    progs["model step"] = jit(st.model_step, params, norm, carry, sds((spec.step_actions, A), jnp.float32), key,
                              sds((), jnp.float32))
    return progs


def chunk_flops(cfg, *, action_space, data_fps: float | None) -> dict[str, float]:
    """FLOPs of one rollout chunk of one episode: {"total", "first_step" (everything with S = 1: caches, one FD and
    one ID Euler step, decode), "per_step" (one FD + one ID network evaluation), "steps"}. The DiT's only with a Wan
    VAE tokenizer (``shape_only_vae``; ``vae_costs`` has the VAE's). ``action_space``: the model's
    (None: ``cost_robot``'s stand-in); the imagined state and the pose condition have its dimension."""
    c = _counting_cfg(cfg)
    with shape_only_vae(c):
        progs = chunk_programs(c, action_space=action_space, data_fps=data_fps)
        fd, idm, first = (xla_cost.flops(progs[k].lower(), False) for k in ("forward step", "inverse step",
                                                                            "model step"))
    S, S_id = cfg.sample.steps, cfg.sample.inverse_steps or cfg.sample.steps
    return {"total": first + (S - 1) * fd + (S_id - 1) * idm, "first_step": first, "per_step": fd + idm,
            "steps": S, "inverse_steps": S_id}


CHUNK_PARTS = ("tokenizer encode", "context encoding", "forward step", "inverse encoding", "inverse step",
               "tokenizer decode", "policy")


def chunk_ideal_flops(cfg, *, action_space, data_fps: float | None) -> dict[str, float]:
    """The matmul FLOPs one chunk of one episode needs, per part of ``chunk_programs``: every clean token's
    keys/values computed once (the context's and forward mode's clean actions in "context encoding", the predicted
    frames' as clean tokens in "inverse encoding", none twice), each Euler step running only its noisy tokens
    against every key, attention counted over the pairs the mask allows, and the last layer's queries, output
    projection and MLP skipped where only keys/values are wanted. A pixel tokenizer's encode and decode are reshapes
    (0); the policy is not ours to trim (its own count stands)."""
    from sc3_jax.rollout import rollout
    from sc3_jax.model.tokenizer import make_tokenizer, window_tokens

    m = cfg.model
    fps, space = cost_robot(cfg, action_space, data_fps)
    spec = rollout.make_spec(cfg, fps, num_chunks=1, action_space=space)
    tok = make_tokenizer(m)
    Kt, Tt = window_tokens(tok, spec.context, spec.predict)
    P, token_dim = math.prod(tok.grid(spec.image_size)), tok.token_dim
    d, L, T, A = m.dim, m.depth, spec.predict, spec.action_dim
    kv = 2 * 2 * d * m.num_kv_heads * m.head_dim  # key and value projections of one token, one layer
    token = kv + 2 * 2 * d * m.num_heads * m.head_dim + 3 * 2 * d * m.mlp_dim  # + queries, output, gated MLP
    pair = 2 * 2 * m.num_heads * m.head_dim  # q.k and p.v of one (query, key) pair, one layer

    def stack(n, keys, kv_only=False):  # n tokens, each attending to ``keys`` keys, through every layer
        full = n * token + n * keys * pair
        return (L - 1) * full + n * kv if kv_only else L * full

    nc, nf = spec.views * (Kt + spec.anchor) * P, spec.views * Tt * P  # context, future video tokens
    video_in, action_in = 2 * token_dim * d, 2 * A * d  # input projections per token (outputs: the same sizes)
    return {"context encoding": nc * video_in + stack(nc, nc, True) + T * action_in + stack(T, nc + T, True),
            "forward step": nf * (2 * video_in) + stack(nf, nc + nf + T),
            "inverse encoding": nf * video_in + stack(nf, nc + nf, True),
            "inverse step": T * (2 * action_in) + stack(T, nc + nf + T),
            "tokenizer encode": 0.0, "tokenizer decode": 0.0}


def chunk_account(cfg, depths: tuple[int, int] = (2, 3), cache: bool = True, *, action_space,
                  data_fps: float | None) -> dict:
    """Compiled FLOPs and bytes accessed (XLA's cost analysis) and the compiled temp memory of every part of one
    rollout chunk of one episode (``chunk_programs``, the layers unrolled, dense attention: the count must see
    every layer and every score), beside the ideal FLOPs (``chunk_ideal_flops``). Parts are compiled at the
    model's depth when it is at most ``depths[1]``, else at both ``depths`` and extrapolated linearly to it (the
    layers are identical; "depth" in the result says which). Per chunk a part runs ``runs`` times (the Euler
    steps S, sample.inverse_steps); "chunk" is the whole model step compiled at S = 1 plus the other S - 1 steps of
    each sampler, plus the policy (the sum of the parts is its check)."""
    import jax

    from sc3_jax.core.config import replace

    c = _counting_cfg(cfg)
    L = c.model.depth
    counted = (L,) if L <= depths[1] else depths

    def costs(depth):
        out = {}
        cd = replace(c, model=dict(depth=depth))
        with shape_only_vae(cd):
            progs = chunk_programs(cd, action_space=action_space, data_fps=data_fps, cache=cache)
        for name, traced in progs.items():
            compiled = traced.lower().compile()
            ca = compiled.cost_analysis()
            ca = ca[0] if isinstance(ca, (list, tuple)) else ca
            out[name] = (float(ca.get("flops", 0.0)), float(ca.get("bytes accessed", 0.0)),
                         float(compiled.memory_analysis().temp_size_in_bytes))
        return out

    at = [costs(dd) for dd in counted]
    if len(at) == 1:
        cost = at[0]
    else:
        (d1, d2), (lo, hi) = counted, at
        cost = {k: tuple(a + (L - d1) * (b - a) / (d2 - d1) for a, b in zip(lo[k], hi[k])) for k in lo}
        cost = {k: (*v[:2], hi[k][2]) for k, v in cost.items()}  # temp memory: as compiled at the larger depth
    with shape_only_vae(c):
        ideal = chunk_ideal_flops(c, action_space=action_space, data_fps=data_fps)
    S, S_id = cfg.sample.steps, cfg.sample.inverse_steps or cfg.sample.steps
    runs = {"forward step": S, "inverse step": S_id}
    if cfg.model.tokenizer != "pixel":  # a learned tokenizer: encoding the context and decoding the kept frames is
        ideal.update({k: cost[k][0] for k in ("tokenizer encode", "tokenizer decode")})  # each frame once
    ideal["policy"] = cost["policy"][0]
    parts = {k: {"runs": runs.get(k, 1), "flops": cost[k][0] if k in cost else 0.0,
                 "bytes": cost[k][1] if k in cost else 0.0, "temp_bytes": cost[k][2] if k in cost else 0.0,
                 "ideal_flops": ideal[k]} for k in CHUNK_PARTS}
    whole = lambda i: (cost["model step"][i] + (S - 1) * cost["forward step"][i]  # noqa: E731
                       + (S_id - 1) * cost["inverse step"][i] + cost["policy"][i])
    ideal_total = sum(p["runs"] * p["ideal_flops"] for p in parts.values())
    return {"parts": parts, "depth": L, "counted_depths": counted, "steps": (S, S_id), "cache": cache,
            "chunk_flops": whole(0), "chunk_bytes": whole(1), "model_step_temp_bytes": cost["model step"][2],
            "parts_flops": sum(p["runs"] * p["flops"] for p in parts.values()), "ideal_flops": ideal_total,
            "ratio": whole(0) / ideal_total, "attention_impl": cfg.model.attention_impl}


def state_bytes(cfg, mesh_cfg) -> dict[str, float]:
    """Per-device bytes of params, optimizer state and the rest of the train state, from the sharding rules on an
    abstract mesh of the requested sizes (a dimension that does not divide by its mesh axes is replicated, as in
    ``sharding.logical_spec``)."""
    import jax
    from jax.sharding import AbstractMesh, AxisType

    from sc3_jax.model import sharding
    from sc3_jax.train import train

    names = sharding.mesh_axes(mesh_cfg)
    sizes = dict(zip(names, sharding.mesh_shape(mesh_cfg, math.prod(_sizes(mesh_cfg).values()))))
    mesh = AbstractMesh(tuple(sizes.values()), names, axis_types=(AxisType.Auto,) * len(names))
    with shape_only_vae(cfg):
        abstract = jax.eval_shape(lambda: train.init_state(cfg))
        axes_list = train.state_axes(cfg, abstract)
    flat, _ = jax.tree_util.tree_flatten_with_path(abstract)
    out = {"params": 0.0, "optimizer": 0.0, "other": 0.0}
    for (path, x), axes in zip(flat, axes_list):
        spec = sharding.logical_spec(axes, x.shape, mesh)
        shard = list(x.shape)
        for i, entry in enumerate(tuple(spec) + (None,) * (x.ndim - len(spec))):
            names_i = (entry,) if isinstance(entry, str) else tuple(entry or ())
            shard[i] = -(-shard[i] // math.prod(sizes[n] for n in names_i))
        top = getattr(path[0], "key", None)
        kind = "params" if top == "params" else "optimizer" if top == "opt_state" else "other"
        out[kind] += math.prod(shard) * x.dtype.itemsize
    return out


def _sizes(mesh_cfg) -> dict[str, int]:
    return {k: getattr(mesh_cfg, k) for k in MESH_KEYS}


FLASH_IMPLS = ("blockwise", "fused", "context_parallel", "ring")  # no [N, M] scores (context parallel: per device)


def activation_estimate(cfg, mesh_cfg) -> float:
    """Analytic per-device activation bytes of one train step (an estimate; checked against compiled memory
    analysis in docs/plan.md). Tokens per device = (micro-batch / (data x fsdp)) x (tokens per sample / context)
    [the sequence is split only by the context-parallel impls]; heads and mlp divided by "tensor".

    Kept for the backward pass, per layer and token, by ``model.remat``:
      "none":  the block's saved tensors (norm inputs and outputs, q/k/v before and after norm and rotary,
               attention output, residuals, the MLP's gate/up/activation/product: 5 D + 4 hd (Hq + 2 Hkv) + 5 mlp
               elements, counts fitted to the compiled CPU step's memory analysis, docs/plan.md) and, with dense
               attention, the fp32 scores and probabilities [Hq, Nq, Nk] (with the blockwise / fused kernels:
               only the softmax statistics, 2 fp32 per head);
      "dots":  the weight matmul outputs: layer input, q/k/v projections, attention and MLP projections
               (2 D + hd (Hq + 2 Hkv) + mlp elements, fitted likewise) -- the attention kernel is recomputed;
      "block": the layer input (D).
    Plus one layer's working set during its backward: its saved tensors and the attention transients (dense:
    scores, their gradient, probabilities; blockwise: fp32 dq and the per-tile scores)."""
    import jax.numpy as jnp

    from sc3_jax.model import tokenizer

    m, s = cfg.model, _sizes(mesh_cfg)
    a = jnp.dtype(m.dtype).itemsize
    with shape_only_vae(cfg):
        N = tokenizer.tokens_per_sample(cfg)
    Bl = -(-(cfg.data.batch_size // cfg.train.grad_accum) // (s["data"] * s["fsdp"]))  # one micro-batch
    C = s["context"] if m.attention_impl in ("context_parallel", "ring") else 1
    Nl = -(-N // C)
    t = s["tensor"]
    split = m.num_kv_heads % t == 0
    hq, hkv = (m.num_heads // t, m.num_kv_heads // t) if split else (m.num_heads, m.num_kv_heads)
    mlp = m.mlp_dim // t if m.mlp_dim % t == 0 else m.mlp_dim
    D, hd = m.dim, m.head_dim
    flash = m.attention_impl in FLASH_IMPLS
    per_token = a * (5 * D + 4 * hd * (hq + 2 * hkv) + 5 * mlp) + (8 * hq if flash else 0)
    if flash:  # fp32 dq [Hq, Nl, hd] (carry + one key block's contribution) and ~12 [bq, bk] fp32 tiles (scores,
        # probabilities, their gradients, ... in the backward's loops; the count fitted to compiled CPU memory)
        b = m.attention_block
        transient = Bl * hq * (2 * Nl * hd * 4 + 12 * min(b, Nl) * min(b, N) * 4)
        kept_scores = 0
    else:
        transient = Bl * hq * Nl * N * (4 + 4 + a)
        kept_scores = Bl * hq * Nl * N * (4 + a)
    working = Bl * Nl * per_token + transient
    kept = {"none": Bl * Nl * per_token + kept_scores,
            "dots": Bl * Nl * a * (2 * D + hd * (hq + 2 * hkv) + mlp),
            "block": Bl * Nl * a * D}[m.remat]
    return m.depth * kept + working


def _microbatches(cfg, mesh_cfg, free: float) -> int | None:
    """The fewest micro-batches (a divisor of the per-device batch) whose estimated activations fit in ``free``
    bytes; None if even one sample per device does not fit."""
    s = _sizes(mesh_cfg)
    per_device = cfg.data.batch_size // (s["data"] * s["fsdp"])
    for k in range(1, per_device + 1):
        if per_device % k == 0:
            smaller = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, grad_accum=k))
            if activation_estimate(smaller, mesh_cfg) <= free:
                return k
    return None


def fitting_plan(cfg, mesh_cfg, device: str, free: float) -> dict | None:
    """The cheapest (attention_impl, remat, micro-batches) whose estimated activations fit in ``free`` bytes:
    dense attention is replaced by the memory-efficient kernel for the device ("fused": cuDNN on GPUs,
    "blockwise" on TPU until splash attention is wired in; other impls are kept); the lightest remat
    (none < dots < block: each recomputes more of the forward pass); then the fewest micro-batches. None if
    nothing fits."""
    from sc3_jax.core.config import REMAT_POLICIES

    m = cfg.model
    impl = m.attention_impl
    if impl == "dense":  # never worth keeping when memory binds: same math, no [N, N] scores
        impl = "blockwise" if device in ("v5p", "cpu") else "fused"
    for remat in REMAT_POLICIES:
        c = dataclasses.replace(cfg, model=dataclasses.replace(m, attention_impl=impl, remat=remat))
        k = _microbatches(c, mesh_cfg, free)
        if k is not None:
            c = dataclasses.replace(c, train=dataclasses.replace(c.train, grad_accum=k))
            return {"attention_impl": impl, "remat": remat, "microbatches": k,
                    "activations_bytes": activation_estimate(c, mesh_cfg), "cfg": c}
    return None


def available_bytes() -> tuple[float, str]:
    """(bytes one device of this machine may use, what they are): an accelerator's memory limit, or the host's
    available memory shared by its CPU devices."""
    import jax

    dev = jax.local_devices()[0]
    stats = dev.memory_stats() if dev.platform != "cpu" else None
    if stats and stats.get("bytes_limit"):
        return float(stats["bytes_limit"]), f"{dev.device_kind} memory"
    with open("/proc/meminfo") as f:
        avail = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    n = jax.local_device_count()
    return avail / n, f"the host's available memory{f' over {n} CPU devices' if n > 1 else ''}"


def fit_to_memory(cfg, num_devices: int, fixed=frozenset()):
    """(config, note) for training ``cfg`` on ``cfg.mesh`` over ``num_devices`` on this machine, decided before
    anything compiles: ``cfg`` itself (note None) when its estimated train step (train state + activations, per
    device) fits a device here; else the cheapest memory plan that fits (``fitting_plan``: the memory-efficient
    attention kernel, remat, micro-batches -- the same model and the same math) and a line saying so. Refused in one
    line naming the estimate, the memory and the flags that fit when nothing fits, or when the plan would change a
    field in ``fixed`` (the ones the user set: ``model.attention_impl``, ...)."""
    import jax

    from sc3_jax.model import sharding

    names = sharding.mesh_axes(cfg.mesh)
    mesh_cfg = dataclasses.replace(cfg.mesh, **dict(zip(names, sharding.mesh_shape(cfg.mesh, num_devices))))
    with shape_only_vae(cfg):
        from sc3_jax.model import tokenizer
        tokens = tokenizer.tokens_per_sample(cfg)
    state, act = sum(state_bytes(cfg, mesh_cfg).values()), activation_estimate(cfg, mesh_cfg)
    free, what = available_bytes()
    if state + act <= free:
        return cfg, None
    need = (f"the train step needs about {(state + act) / 1e9:.1f} GB per device ({tokens} tokens per sample, batch "
            f"{cfg.data.batch_size}, {cfg.model.attention_impl} attention, remat {cfg.model.remat}), a device here "
            f"has {free / 1e9:.1f} GB ({what})")
    fit = fitting_plan(cfg, mesh_cfg, "cpu" if jax.local_devices()[0].platform == "cpu" else "gpu", free - state)
    if fit is None:
        raise UserError(f"{need}: nothing fits at this batch; lower --batch, --data.image-size or the "
                        "model's width")
    changed = {k for k, old, new in (("model.attention_impl", cfg.model.attention_impl, fit["attention_impl"]),
                                     ("model.remat", cfg.model.remat, fit["remat"]),
                                     ("train.grad_accum", cfg.train.grad_accum, fit["microbatches"])) if old != new}
    about = f"{_fit_flags(fit)} (about {(state + fit['activations_bytes']) / 1e9:.1f} GB)"
    if changed & set(fixed):
        raise UserError(f"{need}: it fits with {about}")
    return fit["cfg"], f"{need}: training with {about}, the same model and math in less memory"


def compiled_memory(cfg, mesh_cfg):
    """The compiled train step's per-device memory analysis on this machine's devices (None if they are too
    few)."""
    import jax

    from sc3_jax.model import sharding
    from sc3_jax.train import train

    n = math.prod(_sizes(mesh_cfg).values())
    if n > jax.device_count():
        return None
    mesh = sharding.make_mesh(mesh_cfg, jax.devices()[:n])
    with shape_only_vae(cfg):  # the DiT's step (a Wan VAE's encode is not in it)
        step, _ = train.compile_train_step(cfg, mesh)
        abstract = jax.eval_shape(lambda: train.init_state(cfg))
        return step.lower(abstract, train.batch_shapes(cfg)).compile().memory_analysis()


# ----------------------------------------------------------------------------------------------------------------
# The plan
# ----------------------------------------------------------------------------------------------------------------
def shape_of(cfg, action_space=None) -> dict:
    """What the plan is for: views, image size, window in frames and token frames, tokens per frame, actions."""
    from sc3_jax.model.tokenizer import make_tokenizer, window_tokens

    d, m = cfg.data, cfg.model
    space = cost_robot(cfg, action_space, None)[1]
    with shape_only_vae(cfg):
        tok = make_tokenizer(m)
        rows, cols = tok.grid(d.image_size)
        Kt, Tt = window_tokens(tok, d.context_frames, d.future_frames)
        token_dim = tok.token_dim
    return {"views": list(d.views), "image_size": list(d.image_size), "context_frames": d.context_frames,
            "future_frames": d.future_frames, "context_token_frames": Kt, "future_token_frames": Tt,
            "grid": [rows, cols], "token_dim": token_dim, "tokenizer": m.tokenizer, "patch_size": m.patch_size,
            "time_compression": tok.time_compression,
            "spatial_ratio": vae_config(m).spatial_ratio if m.tokenizer in WAN else None,
            "action_dim": m.action_dim, "action_kind": None if action_space is None else space.kind,
            # the imagined state lives in the action's space (data/action_space.py): the pose condition and the
            # state a policy observes in a rollout have the action's dimension
            "state_dim": space.dim}


def plan(cfg, mesh_cfg, device: str, mfu: float = 0.4, compile: bool = False, chunk: bool = True,
         *, action_space, data_fps: float | None) -> dict:
    """The plan of ``cfg`` on ``mesh_cfg`` x ``device`` (see the module docstring). ``action_space``: the model's
    (a store's declaration; None: ``cost_robot``'s stand-in); ``data_fps``: its data's frame rate (the rollout's
    frame stride)."""
    import jax

    from sc3_jax.model import dit

    if device not in DEVICES:
        raise UserError(f"--device: unknown device {device!r}; known: {', '.join(DEVICES)}")
    if not 0 < mfu <= 1:
        raise UserError(f"--mfu must be in (0, 1], got {mfu}")
    peak, hbm = DEVICES[device]
    sizes = _sizes(mesh_cfg)
    n = math.prod(sizes.values())
    if cfg.data.batch_size % (sizes["data"] * sizes["fsdp"]):
        raise UserError(f"--batch: global batch {cfg.data.batch_size} does not divide over data x fsdp = "
                        f"{sizes['data'] * sizes['fsdp']} of --mesh; change either")
    if action_space is not None and action_space.dim != cfg.model.action_dim:
        raise UserError(f"model.action_dim={cfg.model.action_dim}, but the action space is {action_space.dim}-D "
                        f"{action_space.kind}")
    check_shape(cfg, chunk, action_space=action_space, data_fps=data_fps)
    from sc3_jax.model import checkpoint
    from sc3_jax.model import tokenizer

    cfg = dataclasses.replace(cfg, mesh=mesh_cfg)
    with shape_only_vae(cfg):
        params = checkpoint.param_shapes(cfg)
        tokens = tokenizer.tokens_per_sample(cfg)
    vae = vae_costs(cfg)
    out = {"config": cfg.name, "mesh": sizes, "devices": n, "device": device, "peak_flops": peak, "hbm_bytes": hbm,
           "mfu": mfu, "params": dit.count_params(params), "param_dtype": cfg.model.param_dtype,
           "shape": shape_of(cfg, action_space), "tokens_per_sample": tokens, "batch": cfg.data.batch_size,
           "steps": cfg.train.steps, "attention_impl": cfg.model.attention_impl,
           "notes": [n for n in (vae_note(cfg.model),) if n]}
    out.update({f"{k}_bytes": v for k, v in state_bytes(cfg, mesh_cfg).items()})
    out["grads_bytes"] = out["params_bytes"]  # gradients: one more param-sized, param-sharded tree during the step
    # sc3 train encodes a Wan VAE's frames inside the step: its encoder's weights are constants there, on every device
    out["tokenizer_bytes"] = vae["encoder_bytes"] if vae else 0.0
    mem = compiled_memory(cfg, mesh_cfg) if compile else None
    if mem is not None:
        out["activations_bytes"], out["activations_source"] = float(mem.temp_size_in_bytes), "compiled"
        out["activations_estimate"] = activation_estimate(cfg, mesh_cfg)  # printed beside it: the estimate's check
    else:
        out["activations_bytes"], out["activations_source"] = activation_estimate(cfg, mesh_cfg), "estimate"
        if compile:
            out["notes"].append(f"mesh of {n} devices > {jax.device_count()} local devices: activations estimated")
    out["total_bytes"] = sum(out[f"{k}_bytes"] for k in MEMORY_PARTS)
    if sizes["context"] > 1 and cfg.model.attention_impl == "dense":
        out["notes"].append("mesh has context > 1 but model.attention_impl is 'dense': the sequence is not split "
                            f"(use {config_flag('model.attention_impl', 'ring')})")
    out["fits"] = out["total_bytes"] <= 0.9 * hbm
    out["flops_source"] = "compiled" if compile else "lowered"
    out["step_flops"] = train_step_flops(cfg, compiled=compile)
    out["step_seconds"] = out["step_flops"] / (n * peak * mfu)
    out["train_seconds"] = out["step_seconds"] * cfg.train.steps
    out["fit"] = None
    if not out["fits"]:
        fit = fitting_plan(cfg, mesh_cfg, device, 0.9 * hbm - (out["total_bytes"] - out["activations_bytes"]))
        if fit is not None:
            fit["total_bytes"] = out["total_bytes"] - out["activations_bytes"] + fit["activations_bytes"]
            # remat changes the recomputed FLOPs (attention impl and micro-batches do not: same counted program)
            fit["step_flops"] = (out["step_flops"] if fit["remat"] == cfg.model.remat
                                 else train_step_flops(fit["cfg"], compiled=compile))
            fit["step_seconds"] = fit["step_flops"] / (n * peak * mfu)
            fit["train_seconds"] = fit["step_seconds"] * cfg.train.steps
        out["fit"] = fit
    out["vae"] = None
    if vae:
        views = len(cfg.data.views)
        out["vae"] = {**vae, "step_encode_flops": cfg.data.batch_size * views * vae["video_window_encode_flops"],
                      "chunk_encode_flops": views * vae["video_context_encode_flops"],
                      "chunk_decode_flops": views * vae["video_decode_flops"]}
        out["vae"]["step_encode_seconds"] = out["vae"]["step_encode_flops"] / (n * peak * mfu)
    if chunk:
        c = chunk_flops(cfg, action_space=action_space, data_fps=data_fps)
        out["chunk_model_flops"], out["chunk_steps"] = c["total"], c["steps"]
        out["chunk_inverse_steps"] = c["inverse_steps"]
        out["chunk_flops"] = c["total"] + (out["vae"]["chunk_encode_flops"] + out["vae"]["chunk_decode_flops"]
                                           if vae else 0.0)
        out["chunk_predict"] = cfg.data.future_frames
        out["chunk_seconds"] = out["chunk_flops"] / (peak * mfu)
    return out


MEMORY_PARTS = ("params", "optimizer", "other", "grads", "tokenizer", "activations")


def _gb(x: float) -> str:
    return f"{x / 1e9:9.2f} GB"


def format_plan(p: dict) -> str:
    s = p["mesh"]
    mesh = " ".join(f"{k}={v}" for k, v in s.items())
    peak_note = "approximate vendor dense-BF16 peak"
    lines = [
        (f"plan: config {p['config']}, mesh {mesh} ({p['devices']} devices), device {p['device']} "
         f"({p['peak_flops'] / 1e12:.0f} TFLOP/s {peak_note}, {p['hbm_bytes'] / 1e9:.0f} GB HBM), MFU {p['mfu']:.2f}"),
        f"parameters: {p['params']:,} ({p['params'] / 1e9:.3f} B, {p['param_dtype']})",
        format_shape(p["shape"]),
        (f"tokens: {p['tokens_per_sample']:,} per sample x global batch {p['batch']} = "
         f"{p['tokens_per_sample'] * p['batch']:,} per step; attention {p['attention_impl']}"),
        "per-device memory (train step):",
        f"  params       {_gb(p['params_bytes'])}",
        f"  optimizer    {_gb(p['optimizer_bytes'])}",
        f"  gradients    {_gb(p['grads_bytes'])}  (param-sized, param-sharded)",
    ] + ([f"  tokenizer    {_gb(p['tokenizer_bytes'])}  ({p['vae']['name']} VAE encoder weights, "
          f"{p['vae']['dtype']}, on every device: sc3 train encodes frames inside the step)"] if p["vae"] else []) + [
        f"  activations  {_gb(p['activations_bytes'])}  ("
        + (f"compiled memory analysis: temp buffers per device; estimate {p['activations_estimate'] / 1e9:.3g} GB"
           if p["activations_source"] == "compiled"
           else "ESTIMATE, analytic: plan.activation_estimate") + ")",
        f"  total        {_gb(p['total_bytes'])}  of {p['hbm_bytes'] / 1e9:.0f} GB: "
        + ("fits (<= 90%)" if p["fits"] else "DOES NOT FIT"
           + ("" if p["fit"] else "; nothing fits, not even one sample per device with every remat and the "
              "memory-efficient attention: split the sequence (context axis, attention_impl ring) or shard more")),
        (f"train step: {p['step_flops']:.4g} FLOPs ({p['flops_source']} XLA cost analysis, global), "
         f"{p['step_flops'] / p['devices']:.4g} per device (global / {p['devices']} devices, perfect split)"),
        (f"  at MFU {p['mfu']:.2f}: {p['step_seconds']:.3g} s/step; {p['steps']:,} steps = "
         f"{p['train_seconds'] / 3600:.1f} h = {p['train_seconds'] / 86400:.2f} days on {p['devices']} x "
         f"{p['device']}"),
    ]
    if p["vae"]:
        v, sh = p["vae"], p["shape"]
        lines.append(f"  + {v['name']} VAE encode inside the step: {v['step_encode_flops']:.4g} FLOPs "
                     f"({v['step_encode_flops'] / p['step_flops']:.3g}x the DiT step's; {p['batch']} x "
                     f"{len(sh['views'])} videos of {sh['context_frames'] + sh['future_frames']}"
                     f" frames), >= {v['step_encode_seconds']:.3g} s/step more ({v['dtype']} convolutions at "
                     f"precision {v['precision']!r}: the bf16 peak is a lower bound); not in the step's FLOPs above "
                     "nor its activation estimate")
    if p["fit"]:
        f = p["fit"]
        lines += [f"plan that fits: attention {f['attention_impl']}, remat {f['remat']}, {f['microbatches']} "
                  f"micro-batch{'es' if f['microbatches'] > 1 else ''} per step ({_fit_flags(f)})",
                  f"  activations  {_gb(f['activations_bytes'])}  (ESTIMATE), total {_gb(f['total_bytes']).strip()} "
                  f"of {p['hbm_bytes'] / 1e9:.0f} GB",
                  f"  train step: {f['step_flops']:.4g} FLOPs; at MFU {p['mfu']:.2f}: {f['step_seconds']:.3g} s/step; "
                  f"{p['steps']:,} steps = {f['train_seconds'] / 86400:.2f} days on {p['devices']} x {p['device']}"]
    if "chunk_flops" in p:
        split = "" if not p["vae"] else (
            f" = DiT {p['chunk_model_flops']:.3g} + VAE encode {p['vae']['chunk_encode_flops']:.3g} (the context) + "
            f"decode {p['vae']['chunk_decode_flops']:.3g} (every token frame)")
        steps = (f"{p['chunk_steps']} Euler steps each" if p["chunk_inverse_steps"] == p["chunk_steps"] else
                 f"{p['chunk_steps']} + {p['chunk_inverse_steps']} Euler steps (--sample-steps, --inverse-steps)")
        lines.append(f"rollout chunk (1 episode, {p['chunk_predict']} frames, FD + ID sampling, {steps}): "
                     f"{p['chunk_flops']:.4g} FLOPs{split} (lowered XLA cost analysis)")
        lines.append(f"  at MFU {p['mfu']:.2f} on one {p['device']}: {p['chunk_seconds']:.3g} s/chunk")
    lines += [f"note: {n}" for n in p["notes"]]
    lines.append(verdict(p))
    return "\n".join(lines)


def format_shape(sh: dict) -> str:
    """The shape line: views, image size, window in frames and tokens, actions."""
    H, W = sh["image_size"]
    rows, cols = sh["grid"]
    if sh["time_compression"] > 1:
        window = (f"window {sh['context_frames']} + {sh['future_frames']} frames = {sh['context_token_frames']} + "
                  f"{sh['future_token_frames']} token frames")
        how = (f"{sh['tokenizer']} VAE: {sh['spatial_ratio']}x space, {sh['time_compression']}x time; latent patch "
               f"{sh['patch_size']}")
    else:
        window = f"window {sh['context_frames']} + {sh['future_frames']} frames"
        how = f"{sh['tokenizer']} tokenizer, patch {sh['patch_size']}"
    state = " (end-effector pose)" if sh["action_kind"] == "delta_ee" else ""
    kind = sh["action_kind"] or "(kind: the data's, --data)"
    return (f"shape: {len(sh['views'])} views ({' '.join(sh['views'])}) at {H}x{W}; {window} of {rows} x {cols} = "
            f"{rows * cols:,} tokens ({how}; token dim {sh['token_dim']}); {sh['future_frames']} actions of "
            f"{sh['action_dim']}-D {kind}, imagined state {sh['state_dim']}-D{state}")


def _fit_flags(fit: dict) -> str:
    return " ".join(config_flag(k, v) for k, v in (("model.attention_impl", fit["attention_impl"]),
                                                   ("model.remat", fit["remat"]),
                                                   ("train.grad_accum", fit["microbatches"])))


def verdict(p: dict) -> str:
    """The plan in one line: whether the train step fits in 90% of the device's memory, what takes the memory when
    it does not, and the options that make it fit."""
    budget = 0.9 * p["hbm_bytes"]
    where = f"{p['devices']} x {p['device']}"
    if p["fits"]:
        return (f"verdict: fits on {where}: {p['total_bytes'] / 1e9:.2f} GB per device of a {budget / 1e9:.0f} GB "
                f"budget (90% of HBM); memory is per device, FLOPs global, times assume MFU {p['mfu']:.2f}")
    parts = {k: p.get(f"{k}_bytes", 0.0) for k in MEMORY_PARTS}  # tokenizer: 0 where absent (no Wan VAE)
    big = max(parts, key=parts.get)
    why = (f"does not fit on {where}: {p['total_bytes'] / 1e9:.2f} GB per device > {budget / 1e9:.0f} GB (90% of "
           f"HBM), {big} {parts[big] / 1e9:.2f} GB of it")
    if p["fit"]:
        return f"verdict: {why}; it fits with {_fit_flags(p['fit'])}"
    return (f"verdict: {why}; no attention kernel, remat or micro-batching fits: split the sequence (--mesh "
            f"...,context=N {config_flag('model.attention_impl', 'ring')}) or shard over more devices")
