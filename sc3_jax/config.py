"""Frozen dataclass configs. Named experiment configs live in ``configs/<name>.py`` (each defines ``get_config()``);
any field can be overridden from the command line (``sc3 train --config tiny --train.steps 100``)."""
from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path


ATTENTION_IMPLS = ("dense", "blockwise", "fused", "context_parallel", "ring")
REMAT_POLICIES = ("none", "dots", "block")  # lightest to heaviest recompute


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    dim: int = 128
    depth: int = 4
    num_heads: int = 4
    num_kv_heads: int = 2
    head_dim: int = 32
    mlp_dim: int = 384
    rope_axes_dim: tuple[int, int, int] = (6, 5, 5)  # (time, row, col) frequency sections; sum = head_dim / 2
    rope_theta: float = 10000.0
    time_embed_dim: int = 256  # sinusoid channels of the noise-level embedding
    norm_eps: float = 1e-6
    # Tokenizer: "pixel" = non-overlapping p x p pixel patches (exact round trip).
    tokenizer: str = "pixel"  # or "conv_ae" (learned autoencoder) / "wan2.1" / "wan2.2" (Wan VAE); patch_size is then
    # the latent patch
    tokenizer_path: str | None = None  # conv_ae: a `sc3 train-tokenizer` output (workdir/tokenizer); Wan: diffusers
    # VAE directory (None: random weights)
    patch_size: int = 4
    channels: int = 3
    num_views: int = 3
    action_dim: int = 7
    num_action_domains: int = 1
    view_embedding: bool = True  # per-view learned embedding on video tokens (off for Cosmos3-compatible configs)
    # Shortcuts that make small models learn dynamics in CPU-minutes (off for Cosmos3-compatible configs; none of
    # them touches the context tokens, so context caching stays exact):
    #  anchor_conditioning: each future frame token also sees the 3x3 neighbourhood of its patch in the last
    #    context frame (channel-concatenation conditioning, as video diffusion models do with conditioning latents);
    #  action_to_frames: future frame K+j's tokens also see action j and the running sum of actions 0..j;
    #  action_reads_frames: action j's token also sees the difference of the two frames it connects (all views).
    # Each feature reads clean tokens only, so no clean token ever depends on a noisy one.
    # Without them, each of these relations must first be discovered through attention.
    anchor_conditioning: bool = False
    action_to_frames: bool = False
    action_reads_frames: bool = False
    # Pose conditioning (the robot's pose is given, not inferred, as in Ctrl-World): the absolute end-effector pose
    # and gripper command of the last context frame and of every future frame -- integrated from the commanded
    # actions by ``imagination_state`` in training and rollouts alike -- embedded and added to all of that frame's
    # video tokens, plus a learned absolute (view, row, col) embedding so a token can tell whether the gripper is
    # near it. Future poses are withheld (a learned "unknown" embedding) whenever the actions are targets (inverse
    # mode), since they are integrated from those very actions.
    pose_conditioning: bool = False
    # Context-noise level embedding (anti-drift, as GameNGen): training noises the clean context frames with a
    # random level (flow.context_noise_max) and tells the model that level; rollouts use a small fixed level
    # (sample.context_noise). Off: context tokens are always exactly clean.
    context_noise: bool = False    # "residual": the network predicts clean future frames as (last context frame + zero-initialised output) and
    # clean actions as (0 + output); the velocity is derived from it. "velocity": predicts eps - x directly
    # (what pretrained Cosmos3 checkpoints do). Residual is what made tiny CPU models learn.
    prediction: str = "residual"
    # "full": every token attends to every token. "causal": context tokens attend only to context, other clean
    # tokens only to clean tokens, noisy tokens to everything; so clean keys/values can be computed once per
    # rollout chunk and reused by every sampler step (the context in forward mode, all frames in inverse mode).
    context_attention: str = "full"
    dtype: str = "float32"  # activation dtype
    param_dtype: str = "float32"
    # Rematerialisation of each layer in the backward pass: "none" (keep every activation), "dots" (keep only the
    # layer's weight matmul outputs, jax.checkpoint_policies.dots_with_no_batch_dims_saveable: recompute norms,
    # rotary, attention and activations), "block" (keep only each layer's input, recompute the whole block).
    # True / False are read as "block" / "none". sc3 plan picks the lightest one that fits.
    remat: str = "none"
    # lax.scan over the stacked layers (one compiled block, fast compiles at any depth). False unrolls the scan:
    # same math; XLA's cost analysis counts a loop body once, so FLOP counting compiles the unrolled form.
    scan_layers: bool = True
    # Attention over the packed token sequence (sc3_jax/model/attention.py). "dense": fp32 scores [Hq, N, M] written
    # out per layer (the default; the only mode before the others existed). "blockwise": flash attention in plain
    # JAX (lax.scan over key blocks, online softmax, flash backward): O(N) memory, any backend. "fused": the cuDNN
    # kernel (jax.nn.dot_product_attention) on GPU where the mask and dtype allow it, else "blockwise". With a mesh
    # that has a ``context`` axis (MeshConfig.context > 1) the token sequence is split over that axis and attention
    # runs under ``jax.shard_map`` (sc3_jax/model/context_parallel.py): "context_parallel" all-gathers keys/values,
    # "ring" passes key/value blocks around the ring; each device runs the blockwise kernel. Same math and
    # parameters in every mode; without a context axis the last two fall back to "blockwise".
    attention_impl: str = "dense"
    attention_block: int = 512  # tokens per query / key tile of the blockwise kernel (static; last tile padded)
    # Cosmos3 compatibility (diffusers ``Cosmos3OmniTransformer``; sc3_jax/model/cosmos3.py, convert.py). With the
    # defaults below nothing changes. ``layout="cosmos3"`` computes what Cosmos3OmniTransformer computes for a packed
    # [text | video | actions] sequence: its mRoPE position ids (text arange(L); then offset L + mrope_margin;
    # video t = offset + frame * base_fps / fps, row/col = patch row/col; action i t = offset + (i + 1) *
    # (base_fps / temporal_compression) / fps, row = col = 0), its timestep convention (sinusoid of
    # floor(1000 t) * timestep_scale), its rotary inverse frequencies, and outputs zeroed at clean tokens. With
    # ``text_pathway`` prompt token ids (``Inputs.text``) run through separate "understanding" weights (causal among
    # text) whose per-layer keys/values every generation token also attends to. Cosmos3-compatible configs turn
    # view_embedding and the shortcuts off and use prediction="velocity".
    layout: str = "sc3"  # "sc3" | "cosmos3"
    text_pathway: bool = False
    vocab_size: int = 0  # text vocabulary (embed_tokens / lm_head rows) when text_pathway
    # the prompt's token ids (from the checkpoint's own text tokenizer, e.g. of "" or of the task family) that every
    # sample is conditioned on when no ``Inputs.text`` is given: lets training and rollouts of a text_pathway model
    # (a converted Cosmos3 checkpoint) run without a tokenizer in the loop. One fixed prompt: no padding, so exact.
    prompt_ids: tuple[int, ...] = ()
    base_fps: float = 24.0  # Cosmos3 position ids: time advances base_fps / fps per (latent) frame
    fps: float = 24.0  # pixel frame rate of a window at stride 1 (a sample's fps is fps / stride)
    temporal_compression: int = 4  # pixel frames per latent frame (Wan VAE: 4); actions per latent frame
    mrope_margin: int = 15000  # gap between the text positions and the first video position
    fps_modulation: bool = True  # False: integer time positions (frame index) as Cosmos3 without fps modulation
    reset_spatial_ids: bool = True  # False: row/col positions also start at the offset
    timestep_scale: float = 0.001

    def __post_init__(self):
        if 2 * sum(self.rope_axes_dim) != self.head_dim:
            raise ValueError(f"rope_axes_dim {self.rope_axes_dim} must sum to head_dim/2 = {self.head_dim // 2}")
        if self.num_heads % self.num_kv_heads:
            raise ValueError("num_heads must be a multiple of num_kv_heads")
        if self.tokenizer not in ("pixel", "conv_ae", "wan2.1", "wan2.2"):
            raise ValueError(f"unknown tokenizer {self.tokenizer!r} (available: 'pixel', 'conv_ae', 'wan2.1', 'wan2.2')")
        if self.pose_conditioning and self.layout != "sc3":
            raise ValueError("pose_conditioning needs layout='sc3'")
        if self.prediction not in ("residual", "velocity"):
            raise ValueError(f"prediction must be 'residual' or 'velocity', got {self.prediction!r}")
        if self.context_attention not in ("full", "causal"):
            raise ValueError(f"context_attention must be 'full' or 'causal', got {self.context_attention!r}")
        if self.attention_impl not in ATTENTION_IMPLS:
            raise ValueError(f"attention_impl must be one of {ATTENTION_IMPLS}, got {self.attention_impl!r}")
        if self.attention_block < 1:
            raise ValueError(f"attention_block must be >= 1, got {self.attention_block}")
        if isinstance(self.remat, bool):  # backward compatible: remat=True / False
            object.__setattr__(self, "remat", "block" if self.remat else "none")
        if self.remat not in REMAT_POLICIES:
            raise ValueError(f"remat must be one of {REMAT_POLICIES} (or a bool), got {self.remat!r}")
        if self.layout not in ("sc3", "cosmos3"):
            raise ValueError(f"layout must be 'sc3' or 'cosmos3', got {self.layout!r}")
        if self.text_pathway and (self.layout != "cosmos3" or self.vocab_size <= 0):
            raise ValueError("text_pathway needs layout='cosmos3' and vocab_size > 0")
        if any(not 0 <= i < self.vocab_size for i in self.prompt_ids):
            raise ValueError(f"prompt_ids must lie in [0, vocab_size={self.vocab_size}), got {self.prompt_ids}")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    path: str = "runs/synthetic/episodes"  # an episode dataset (sc3_jax/data/episodes.py)
    views: tuple[str, ...] = ("left", "right", "wrist")
    image_size: tuple[int, int] = (16, 16)
    context_frames: int = 2  # K clean context frames
    future_frames: int = 4  # l' predicted frames (and actions) per window
    strides: tuple[int, ...] = (1, 2)  # multi-FPS: frame stride drawn per sample from these
    pseudo_action_prob: float = 0.5  # replace recorded actions by ones derived from end-effector poses
    batch_size: int = 8  # global batch
    seed: int = 0
    read_threads: int = 0  # 0 = read in the training thread


@dataclasses.dataclass(frozen=True)
class ModeConfig:
    # Per-sample probabilities of forward dynamics, cross-view inpainting, inverse dynamics.
    probs: tuple[float, float, float] = (0.8, 0.1, 0.1)


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    # Noise levels t are drawn logit-normal (SD3): t = sigmoid(mean + std * n). A positive mean spends more of the
    # training on high noise, where a world model must actually predict from its context and actions.
    t_logit_mean: float = 0.0
    t_logit_std: float = 1.0
    # Per-modality loss weights. Modes mix video-only and action-only losses in one batch; when their scales differ
    # by 10x+ (residual video targets are small), Adam's shared second moments starve the smaller one.
    video_loss_weight: float = 1.0
    action_loss_weight: float = 1.0
    # anti-drift: each sample's clean context frames get x = (1 - s) x + s eps with s ~ U(0, context_noise_max)
    # (needs model.context_noise, which gives s to the model). Loss targets are never noised by it.
    context_noise_max: float = 0.0


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    workdir: str = "runs/tiny"
    steps: int = 2000
    lr: float = 1e-4
    warmup_steps: int = 100
    weight_decay: float = 0.05
    b1: float = 0.9
    b2: float = 0.99
    grad_clip: float = 1.0
    # micro-batches per step (gradient accumulation): activations of batch_size / grad_accum samples at a time,
    # same optimizer update as one big batch up to the per-micro-batch noise draws. sc3 plan says when it is needed.
    grad_accum: int = 1
    # start from these params instead of a random init (a `sc3 train` workdir, an exported world model or a
    # `sc3 convert` output); fresh optimizer, step 0, and the source's action normalisation. Ignored once this
    # run has a checkpoint of its own (resume wins).
    init_from: str | None = None
    seed: int = 0
    log_every: int = 10
    ckpt_every: int = 200
    keep_checkpoints: int = 3
    async_checkpointing: bool = True
    tensorboard: bool = True
    progress: bool = True


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    data: int = -1  # -1: all devices not used by the other axes
    fsdp: int = 1
    tensor: int = 1
    # context parallelism: the token sequence of every sample is split over this many devices (needs
    # model.attention_impl "context_parallel" or "ring"). 1 = no "context" mesh axis at all (meshes as before).
    context: int = 1


@dataclasses.dataclass(frozen=True)
class SampleConfig:
    steps: int = 10  # Euler steps from t = 1 to t = 0
    # Euler steps of the inverse-dynamics re-read in a rollout (None: ``steps``). It only yields U_chunk (never the
    # frames or the outcomes), and it is a third of a rollout's cost at 8 steps: fewer steps make sweeps cheaper
    inverse_steps: int | None = None
    context_noise: float = 0.0  # noise level put on the context at inference (models trained with context noise)


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    policy_chunk: int = 25  # actions proposed per policy call
    keep_frames: int = 16  # l: predicted frames kept as context per chunk (l' = data.future_frames)
    episode_seconds: float = 20.0
    control_hz: float = 10.0  # the model's frame rate in a rollout (frame stride = data fps / control_hz)
    # the policy's action rate (None = control_hz). When higher, each group of policy_hz / control_hz raw actions is
    # composed into one model-rate action (as the data pipeline composes recorded actions for strided windows).
    policy_hz: float | None = None
    tau: float = 0.02  # stop once U_chunk > tau (in tau_units)
    # U_chunk's units, the one convention of `sc3 rollout`, `sc3 sweep` and the report: "raw" (metres / radians /
    # gripper metres, the paper's units for tau = 0.02) or "normalised" (per-dimension unit variance, the model's
    # units; with per-dimension stds of a few mm, U there is ~50-100x the raw value)
    tau_units: str = "raw"


@dataclasses.dataclass(frozen=True)
class Config:
    name: str = "tiny"
    model: ModelConfig = ModelConfig()
    data: DataConfig = DataConfig()
    modes: ModeConfig = ModeConfig()
    flow: FlowConfig = FlowConfig()
    train: TrainConfig = TrainConfig()
    mesh: MeshConfig = MeshConfig()
    sample: SampleConfig = SampleConfig()
    rollout: RolloutConfig = RolloutConfig()


def configs_dir() -> Path:
    return Path(__file__).resolve().parents[1] / "configs"


def available_configs() -> list[str]:
    return sorted(p.stem for p in configs_dir().glob("*.py") if not p.stem.startswith("_"))


def load_config(name_or_path: str) -> Config:
    """``name_or_path`` is a file path or the name of a file in ``configs/``, optionally followed by ``:ARG``
    (passed to its ``get_config(arg)``, e.g. ``ablation_no_id:tiny``)."""
    name_or_path, _, arg = name_or_path.partition(":")
    path = Path(name_or_path)
    if not path.suffix:
        path = configs_dir() / f"{name_or_path}.py"
    if not path.exists():
        raise FileNotFoundError(f"no config {name_or_path!r}; named configs: {', '.join(available_configs())}")
    spec = importlib.util.spec_from_file_location(f"sc3_config_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    cfg = module.get_config(arg or None)
    if not isinstance(cfg, Config):
        raise TypeError(f"{path}: get_config() must return sc3_jax.config.Config, got {type(cfg)}")
    return cfg


def replace(cfg, **sections):
    """``replace(cfg, train=dict(steps=5))``: nested dataclasses.replace for overrides in code and tests."""
    updates = {}
    for key, value in sections.items():
        if isinstance(value, dict):
            updates[key] = dataclasses.replace(getattr(cfg, key), **value)
        else:
            updates[key] = value
    return dataclasses.replace(cfg, **updates)


def config_from_dict(d: dict, default=None):
    """Rebuild a Config from ``dataclasses.asdict`` output (``config.json``); lists become tuples, unknown keys are
    dropped with a warning (configs evolve), missing keys keep their defaults."""
    default = Config() if default is None else default
    changes = {}
    for f in dataclasses.fields(default):
        if f.name not in d:
            continue
        cur, val = getattr(default, f.name), d[f.name]
        if dataclasses.is_dataclass(cur):
            changes[f.name] = config_from_dict(val, cur)
        elif isinstance(cur, tuple):
            changes[f.name] = tuple(tuple(v) if isinstance(v, list) else v for v in val)
        else:
            changes[f.name] = val
    unknown = set(d) - {f.name for f in dataclasses.fields(default)}
    if unknown:
        print(f"config.json: ignoring unknown config fields {sorted(unknown)}", file=sys.stderr)
    return dataclasses.replace(default, **changes)
