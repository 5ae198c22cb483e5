"""The memory model of a train step, per device: the train state from the sharding rules (``state_bytes``), the
activations (``activation_estimate``; compiled: ``compiled_memory``) and the cheapest plan that fits (``fitting_plan``,
``fit_to_memory``)."""
from __future__ import annotations

import dataclasses
import math

from sc3_jax.core.errors import UserError
from sc3_jax.train.config_flag import config_flag
from sc3_jax.train.plan_vae import shape_only_vae

MESH_KEYS = ("data", "fsdp", "tensor", "context")


def state_bytes(cfg, mesh_cfg) -> dict[str, float]:
    """Per-device bytes of params, optimizer state and the rest of the train state, from the sharding rules on an
    abstract mesh of the requested sizes (a dimension that does not divide by its mesh axes is replicated, as in
    ``sharding.logical_spec``)."""
    import jax
    from jax.sharding import AbstractMesh, AxisType

    from sc3_jax.model import sharding
    from sc3_jax.train import train

    names = sharding.mesh_axes(mesh_cfg)
    sizes = dict(zip(names, sharding.mesh_shape(mesh_cfg, math.prod(mesh_sizes(mesh_cfg).values()))))
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


def mesh_sizes(mesh_cfg) -> dict[str, int]:
    """{axis: size} of a MeshConfig, in ``MESH_KEYS`` order."""
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

    m, s = cfg.model, mesh_sizes(mesh_cfg)
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
    s = mesh_sizes(mesh_cfg)
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


def fit_flags(fit: dict) -> str:
    """The options that set a fitting plan (``fitting_plan``), as a user types them."""
    return " ".join(config_flag(k, v) for k, v in (("model.attention_impl", fit["attention_impl"]),
                                                   ("model.remat", fit["remat"]),
                                                   ("train.grad_accum", fit["microbatches"])))



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
    about = f"{fit_flags(fit)} (about {(state + fit['activations_bytes']) / 1e9:.1f} GB)"
    if changed & set(fixed):
        raise UserError(f"{need}: it fits with {about}")
    return fit["cfg"], f"{need}: training with {about}, the same model and math in less memory"


def compiled_memory(cfg, mesh_cfg):
    """The compiled train step's per-device memory analysis on this machine's devices (None if they are too
    few)."""
    import jax

    from sc3_jax.model import sharding
    from sc3_jax.train import train

    n = math.prod(mesh_sizes(mesh_cfg).values())
    if n > jax.device_count():
        return None
    mesh = sharding.make_mesh(mesh_cfg, jax.devices()[:n])
    with shape_only_vae(cfg):  # the DiT's step (a Wan VAE's encode is not in it)
        step, _ = train.compile_train_step(cfg, mesh)
        abstract = jax.eval_shape(lambda: train.init_state(cfg))
        return step.lower(abstract, train.batch_shapes(cfg)).compile().memory_analysis()
