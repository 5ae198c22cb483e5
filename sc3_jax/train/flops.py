"""FLOP accounting by XLA's cost analysis, nothing allocated: one train step (``train_step_flops``) and one rollout
chunk (``chunk_programs``, ``chunk_flops``; per part, beside the ideal count: ``chunk_account``)."""
from __future__ import annotations

import dataclasses
import functools
import math

from sc3_jax.core import xla_cost
from sc3_jax.train.plan_vae import shape_only_vae
from sc3_jax.train.shape_check import cost_robot


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
