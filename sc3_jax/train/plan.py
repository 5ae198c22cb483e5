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
  remat and the fewest micro-batches whose estimate fits (``memory.fitting_plan``), with its own step FLOPs.
* Times: FLOPs / (devices x peak x MFU). Peaks are approximate vendor dense-BF16 figures per chip (``DEVICES``).
* Shape: views, image size, window, action (= imagined state) dimension and tokenizer all come from the config (a
  store's dataset.json, through ``data.shape.shape_from_dataset``, in ``sc3 plan --data``);
  ``shape_check.check_shape`` refuses, in one line naming the field, a shape the model cannot take, before anything
  is traced.
* Wan VAE tokenizers: never allocated; their share is counted apart (``plan_vae.py``).

This module is the plan itself (``plan``, ``format_plan``, ``verdict``); its pieces live in their own modules:
the FLOP account in ``flops.py``, the memory model in ``memory.py``, the shape check in ``shape_check.py``.
"""
from __future__ import annotations

import dataclasses
import math

from sc3_jax.core.errors import UserError
from sc3_jax.train import flops, memory, shape_check
from sc3_jax.train.config_flag import config_flag
from sc3_jax.train.memory import MESH_KEYS
from sc3_jax.train.plan_vae import WAN, shape_only_vae, vae_config, vae_costs, vae_note

# device: (approximate vendor peak dense BF16 FLOP/s per chip, HBM bytes per chip)
DEVICES: dict[str, tuple[float, float]] = {
    "h100": (989e12, 80e9),  # H100 SXM: 989 TFLOP/s dense BF16, 80 GB HBM3
    "h200": (989e12, 141e9),  # H200 SXM: same compute as H100, 141 GB HBM3e
    "gb200": (2.5e15, 186e9),  # one Blackwell GPU of a GB200 NVL72: ~2.5 PFLOP/s dense BF16, ~186 GB HBM3e
    "v5p": (459e12, 95e9),  # TPU v5p chip: 459 TFLOP/s BF16, 95 GB HBM2e
}


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


# ----------------------------------------------------------------------------------------------------------------
# The plan
# ----------------------------------------------------------------------------------------------------------------
def shape_of(cfg, action_space=None) -> dict:
    """What the plan is for: views, image size, window in frames and token frames, tokens per frame, actions."""
    from sc3_jax.model.tokenizer import make_tokenizer, window_tokens

    d, m = cfg.data, cfg.model
    space = shape_check.cost_robot(cfg, action_space, None)[1]
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
    sizes = memory.mesh_sizes(mesh_cfg)
    n = math.prod(sizes.values())
    if cfg.data.batch_size % (sizes["data"] * sizes["fsdp"]):
        raise UserError(f"--batch: global batch {cfg.data.batch_size} does not divide over data x fsdp = "
                        f"{sizes['data'] * sizes['fsdp']} of --mesh; change either")
    if action_space is not None and action_space.dim != cfg.model.action_dim:
        raise UserError(f"model.action_dim={cfg.model.action_dim}, but the action space is {action_space.dim}-D "
                        f"{action_space.kind}")
    shape_check.check_shape(cfg, chunk, action_space=action_space, data_fps=data_fps)
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
    out.update({f"{k}_bytes": v for k, v in memory.state_bytes(cfg, mesh_cfg).items()})
    out["grads_bytes"] = out["params_bytes"]  # gradients: one more param-sized, param-sharded tree during the step
    # sc3 train encodes a Wan VAE's frames inside the step: its encoder's weights are constants there, on every device
    out["tokenizer_bytes"] = vae["encoder_bytes"] if vae else 0.0
    mem = memory.compiled_memory(cfg, mesh_cfg) if compile else None
    if mem is not None:
        out["activations_bytes"], out["activations_source"] = float(mem.temp_size_in_bytes), "compiled"
        # printed beside it: the estimate's check
        out["activations_estimate"] = memory.activation_estimate(cfg, mesh_cfg)
    else:
        out["activations_bytes"], out["activations_source"] = memory.activation_estimate(cfg, mesh_cfg), "estimate"
        if compile:
            out["notes"].append(f"mesh of {n} devices > {jax.device_count()} local devices: activations estimated")
    out["total_bytes"] = sum(out[f"{k}_bytes"] for k in MEMORY_PARTS)
    if sizes["context"] > 1 and cfg.model.attention_impl == "dense":
        out["notes"].append("mesh has context > 1 but model.attention_impl is 'dense': the sequence is not split "
                            f"(use {config_flag('model.attention_impl', 'ring')})")
    out["fits"] = out["total_bytes"] <= 0.9 * hbm
    out["flops_source"] = "compiled" if compile else "lowered"
    out["step_flops"] = flops.train_step_flops(cfg, compiled=compile)
    out["step_seconds"] = out["step_flops"] / (n * peak * mfu)
    out["train_seconds"] = out["step_seconds"] * cfg.train.steps
    out["fit"] = None
    if not out["fits"]:
        fit = memory.fitting_plan(cfg, mesh_cfg, device, 0.9 * hbm - (out["total_bytes"] - out["activations_bytes"]))
        if fit is not None:
            fit["total_bytes"] = out["total_bytes"] - out["activations_bytes"] + fit["activations_bytes"]
            # remat changes the recomputed FLOPs (attention impl and micro-batches do not: same counted program)
            fit["step_flops"] = (out["step_flops"] if fit["remat"] == cfg.model.remat
                                 else flops.train_step_flops(fit["cfg"], compiled=compile))
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
        c = flops.chunk_flops(cfg, action_space=action_space, data_fps=data_fps)
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
           else "ESTIMATE, analytic: memory.activation_estimate") + ")",
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
                  f"micro-batch{'es' if f['microbatches'] > 1 else ''} per step ({memory.fit_flags(f)})",
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
        return f"verdict: {why}; it fits with {memory.fit_flags(p['fit'])}"
    return (f"verdict: {why}; no attention kernel, remat or micro-batching fits: split the sequence (--mesh "
            f"...,context=N {config_flag('model.attention_impl', 'ring')}) or shard over more devices")
