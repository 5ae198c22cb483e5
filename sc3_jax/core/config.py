"""Frozen dataclass configs. Named experiment configs live in ``configs/<name>.py`` (each defines ``get_config()``);
any field can be overridden from the command line (``sc3 train --config tiny --train.steps 100``)."""
from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

from sc3_jax.core.errors import UserError


ATTENTION_IMPLS = ("dense", "blockwise", "fused", "context_parallel", "ring")
REMAT_POLICIES = ("none", "dots", "block")  # lightest to heaviest recompute


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """The world model: the transformer, its tokenizer, and the Cosmos3 conventions it can switch on."""

    dim: int = 128
    """width of the transformer's residual stream (every token's embedding)"""
    depth: int = 4
    """transformer layers (each an attention block and a gated MLP; their parameters are stacked on a leading
    "layers" axis and run with lax.scan: one compiled block whatever the depth)"""
    num_heads: int = 4
    """query heads per attention layer; a multiple of num_kv_heads"""
    num_kv_heads: int = 2
    """key/value heads per attention layer (grouped-query attention: num_heads / num_kv_heads query heads share one)"""
    head_dim: int = 32
    """channels per attention head; twice the sum of rope_axes_dim (the rotary embedding rotates channel pairs, split
    over time, row and column)"""
    mlp_dim: int = 384
    """hidden width of each layer's gated MLP"""
    rope_axes_dim: tuple[int, int, int] = (6, 5, 5)
    """rotary frequencies driven by each position axis (time, row, col), interleaved as Cosmos3 does; must sum to
    head_dim / 2"""
    rope_theta: float = 10000.0
    """rotary base: frequencies are 1 / rope_theta ** (2 i / head_dim)"""
    time_embed_dim: int = 256
    """sinusoid channels of the noise-level embedding (and of the context-noise embedding)"""
    norm_eps: float = 1e-6
    """epsilon of every RMS norm (layer norms, query/key norms, final norm)"""
    tokenizer: str = "pixel"
    """frames <-> tokens: "pixel" (non-overlapping patch_size x patch_size pixel patches: an exact round trip),
    "conv_ae" (a learned conv autoencoder, `sc3 train-tokenizer`), "wan2.1" / "wan2.2" (a Wan VAE, 4x time
    compression)"""
    tokenizer_path: str | None = None
    """conv_ae: a `sc3 train-tokenizer` output (WORKDIR/tokenizer); Wan: a diffusers VAE directory (None: random
    weights, for plumbing only). The pixel tokenizer reads none"""
    patch_size: int = 4
    """side of each token's square patch: in pixels for the "pixel" tokenizer, in latent cells for the learned ones"""
    frame_tokens: int | None = None
    """token budget per frame, every view together: `sc3 train` picks patch_size from the data's image size and view
    count to meet it (sizing.py), so a config costs about the same on any robot. None: patch_size as given"""
    channels: int = 3
    """values per pixel the "pixel" tokenizer packs into a token (3: RGB); a converted Cosmos3 config records its
    VAE's latent channels here (the other tokenizers take theirs from their weights)"""
    num_views: int = 3
    """camera views (len(data.views)) the per-view weights are sized for: the view embedding, the pose-conditioning
    position embedding, the action_reads_frames projection"""
    action_dim: int = 7
    """entries of an action (xyz delta, rotation-vector delta, gripper target) and of an end-effector pose"""
    num_action_domains: int = 1
    """sets of action input/output projection weights, one per embodiment (Cosmos3's num_embodiment_domains); our
    training and rollouts use domain 0"""
    view_embedding: bool = True
    """add a learned per-view embedding to every video token (off for Cosmos3-compatible configs)"""
    # The three shortcuts below make small models learn dynamics in CPU-minutes; without them each relation must
    # first be discovered through attention. Each reads clean tokens only (no clean token ever depends on a noisy
    # one) and none touches the context tokens, so context caching stays exact. Off for Cosmos3-compatible configs.
    anchor_conditioning: bool = False
    """shortcut: each future frame token also sees the 3x3 neighbourhood of its patch in the last context frame
    (channel-concatenation conditioning, as video diffusion models do with conditioning latents)"""
    action_to_frames: bool = False
    """shortcut: future frame K+j's tokens also see (clean) action j and how far the actions 0..j moved the robot
    (model.action_sum)"""
    action_sum: str = "actions"
    """what action_to_frames adds up: "pose" -- the pose condition's displacement since the last context frame
    (physical units over the state's spread: a still arm adds nothing; needs pose_conditioning) -- or "actions", the
    running sum of normalised actions (models saved before "pose": a still arm adds the mean offset every frame)"""
    action_reads_frames: bool = False
    """shortcut: action j's token also sees the difference of the two frames it connects, in every view (when both
    are clean)"""
    pose_conditioning: bool = False
    """give the robot's pose instead of leaving it to be inferred (as Ctrl-World): the end-effector pose and gripper
    command of the last context frame and of every future frame -- integrated from the commanded actions in training
    and rollouts alike -- embedded and added to that frame's video tokens, plus a learned absolute (view, row, col)
    embedding so a token can tell whether the gripper is near it. Future poses are withheld (a learned "unknown"
    embedding) whenever the actions are targets (inverse mode), since they are integrated from those very actions.
    Needs the sc3 layout"""
    context_noise: bool = False
    """tell the model the noise level of its context frames (anti-drift, as GameNGen): training noises the clean
    context with a random level up to flow.context_noise_max, rollouts with sample.context_noise. Off: the context
    is always exactly clean"""
    prediction: str = "residual"
    """how the network's output is read: "residual" predicts clean future frames as (last context frame +
    zero-initialised output) and clean actions as (0 + output), the velocity derived from them -- what made tiny
    CPU models learn; "velocity" predicts eps - x directly (what pretrained Cosmos3 checkpoints do)"""
    context_attention: str = "full"
    """which tokens attend to which: "full": every token to every token. "causal": context tokens only to the
    context, other clean tokens only to clean tokens, noisy tokens to everything; so clean keys/values are computed
    once per rollout chunk and reused by every sampler step (the context in forward mode, all frames in inverse
    mode)"""
    dtype: str = "float32"
    """compute dtype every matmul casts weights and activations to (e.g. "bfloat16"); norms, softmax and the loss
    stay float32"""
    param_dtype: str = "float32"
    """dtype parameters are created in; training needs float32 (the master weights), bfloat16 is a storage format"""
    remat: str = "none"
    """what each layer keeps for the backward pass: "none" (every activation), "dots" (only its weight matmul
    outputs: jax.checkpoint_policies.dots_with_no_batch_dims_saveable recomputes norms, rotary, attention and
    activations), "block" (only its input; the whole block is recomputed). True / False read as "block" / "none";
    `sc3 plan` picks the lightest one that fits"""
    scan_layers: bool = True
    """lax.scan over the stacked layers (one compiled block: fast compiles at any depth). False unrolls the scan:
    same math; XLA's cost analysis counts a loop body once, so FLOP counting compiles the unrolled form"""
    attention_impl: str = "dense"
    """attention over the packed token sequence (sc3_jax/model/attention.py), same math and parameters in every
    mode: "dense" (fp32 scores [Hq, N, M] written out per layer), "blockwise" (flash attention in plain JAX: O(N)
    memory, any backend), "fused" (the cuDNN kernel on GPU where mask and dtype allow, else "blockwise"),
    "context_parallel" / "ring" (the token sequence split over the mesh's context axis, mesh.context > 1: keys/values
    all-gathered / passed around a ring, each device running the blockwise kernel; "blockwise" without that axis)"""
    attention_block: int = 512
    """tokens per query / key tile of the blockwise kernel (static; the last tile padded)"""
    # Cosmos3 compatibility (diffusers Cosmos3OmniTransformer; sc3_jax/model/cosmos3.py, convert.py): with the
    # defaults below nothing changes. Cosmos3-compatible configs also turn view_embedding and the shortcuts off and
    # use prediction="velocity".
    layout: str = "sc3"
    """token layout and position conventions: "sc3" (ours), or "cosmos3": compute what Cosmos3OmniTransformer
    computes for a packed [text | video | actions] sequence -- its mRoPE position ids, its timestep convention
    (sinusoid of floor(1000 t) * timestep_scale), its rotary frequencies, outputs zeroed at clean tokens, any number
    of actions per token frame"""
    text_pathway: bool = False
    """run prompt token ids through separate "understanding" weights (causal among text) whose per-layer
    keys/values every generation token also attends to (Cosmos3; needs layout "cosmos3" and vocab_size > 0)"""
    vocab_size: int = 0
    """text vocabulary: rows of the token embedding and LM head (text_pathway only)"""
    prompt_ids: tuple[int, ...] = ()
    """the prompt's token ids (from the checkpoint's own text tokenizer, e.g. of "" or of the task family) every
    sample is conditioned on when none is given: lets a text_pathway model (a converted Cosmos3 checkpoint) train and
    roll out without a tokenizer in the loop. One fixed prompt: no padding, so exact"""
    base_fps: float = 24.0
    """cosmos3 layout: time positions advance base_fps / fps per (latent) frame"""
    fps: float = 24.0
    """cosmos3 layout: pixel frame rate of a window at stride 1 (a sample's fps is fps / stride)"""
    temporal_compression: int = 4
    """cosmos3 layout: pixel frames per latent frame (Wan VAE: 4), i.e. actions per latent frame, in the time
    positions"""
    mrope_margin: int = 15000
    """cosmos3 layout: gap between the last text position and the first video position"""
    fps_modulation: bool = True
    """cosmos3 layout: time positions scaled by the sample's fps; False: integer time positions (frame index), as
    Cosmos3 without fps modulation"""
    reset_spatial_ids: bool = True
    """cosmos3 layout: row/col positions start at 0; False: they also start at the text offset"""
    timestep_scale: float = 0.001
    """cosmos3 layout: the timestep embedding is a sinusoid of floor(1000 t) * timestep_scale"""

    def __post_init__(self):
        if 2 * sum(self.rope_axes_dim) != self.head_dim:
            raise ValueError(f"rope_axes_dim {self.rope_axes_dim} must sum to head_dim/2 = {self.head_dim // 2}")
        if self.num_heads % self.num_kv_heads:
            raise ValueError("num_heads must be a multiple of num_kv_heads")
        if self.tokenizer not in ("pixel", "conv_ae", "wan2.1", "wan2.2"):
            raise ValueError(f"unknown tokenizer {self.tokenizer!r} (available: 'pixel', 'conv_ae', 'wan2.1', 'wan2.2')")
        if self.pose_conditioning and self.layout != "sc3":
            raise ValueError("pose_conditioning needs layout='sc3'")
        if self.action_sum not in ("actions", "pose"):
            raise ValueError(f"action_sum must be 'actions' or 'pose', got {self.action_sum!r}")
        if self.action_sum == "pose" and self.action_to_frames and not self.pose_conditioning:
            raise ValueError("action_sum 'pose' adds up the pose condition: it needs pose_conditioning")
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
class WindowWeights:
    """Training windows drawn by what happens in them (sc3_jax/data/window_weights.py): a window has an *event* when
    a named entry of the objects' state moves, or a named entry of the robot's state changes, by more than a threshold
    within its frames (at the smallest of data.strides); event windows are then drawn so often that they make up
    `share` of the windows the model sees (each window a whole number of times per epoch, so the order stays
    deterministic and resumable). Nothing robot-specific: the entries are the store's own names (dataset.json)."""

    share: float = 0.0
    """the share of windows with an event among those drawn (e.g. 0.5), in [0, 1); 0: off -- every window once, in
    the uniform order (with entries named, the training run still says the share it has)"""
    objects: tuple[str, ...] = ()
    """entries of the store's object_state (a name from its dataset.json, or an index) whose motion marks an event,
    e.g. block_x block_y block_z (empty: none)"""
    object_motion: float = 0.01
    """an object entry moves when it spans more than this (max - min over the window's frames, in the data's units:
    metres for positions)"""
    state: tuple[str, ...] = ()
    """entries of the robot's recorded state (a name from its dataset.json, or an index) whose change marks an event,
    e.g. gripper (closing or opening) (empty: none)"""
    state_change: float = 0.1
    """a state entry changes when it spans more than this (max - min over the window's frames, in the data's units)"""

    def __post_init__(self):
        if not 0.0 <= self.share < 1.0:
            raise ValueError(f"data.window_weights.share must be in [0, 1) (0: off), got {self.share!r}")
        for name in ("object_motion", "state_change"):
            value = getattr(self, name)
            if not 0.0 <= value < float("inf"):
                raise ValueError(f"data.window_weights.{name} must be a finite number >= 0, got {value!r}")
        if self.share > 0 and not (self.objects or self.state):
            raise ValueError("data.window_weights.share > 0 needs entries that mark an event: name some in "
                             "data.window_weights.objects or data.window_weights.state")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """The training data: which episodes, which views, and how training windows are cut from them."""

    path: str = "runs/synthetic/episodes"
    """the episode dataset to train on (the format of sc3_jax/data/episodes.py: `sc3 demo`, `sc3 sim demos`,
    `sc3 data import-lerobot` write it)"""
    views: tuple[str, ...] = ("left", "right", "wrist")
    """camera views read from the dataset, in the model's view order (`sc3 train` takes them from the dataset's
    dataset.json unless given; this default is the synthetic demo data's, which data-less configs size from)"""
    fps: float | None = None
    """the data's frame rate (None: not known yet). `sc3 train` fills it from the dataset's dataset.json, so a saved
    model's config.json records the frame rate it was trained at (checkpoint.read_robot)"""
    state_dim: int | None = None
    """the size of the robot state the data records (0: none; None: not known yet). `sc3 train` fills it from the
    dataset's dataset.json"""
    image_size: tuple[int, int] = (16, 16)
    """(height, width) of the frames; must match the dataset's"""
    context_frames: int = 2
    """K: clean context frames at the start of each window"""
    future_frames: int = 4
    """l': frames (and actions) predicted per window, after the context"""
    anchor: bool = False
    """memory: the episode's first frame kept in front of every window's context, a clean token frame at its true
    time (in a rollout: the first observation, however many chunks ago), so what the scene held stays in view
    (RoboWorld's anchored context). One token frame per frame (tokenizer 'pixel' or 'conv_ae')"""
    strides: tuple[int, ...] = (1, 2)
    """multi-FPS: each window's frame stride is drawn from these (recorded actions composed over the stride)"""
    pseudo_action_prob: float = 0.5
    """probability that a window's recorded actions are replaced by ones derived from its end-effector poses"""
    batch_size: int = 8
    """global batch (summed over processes and devices); divisible by the process count and by train.grad_accum"""
    seed: int = 0
    """seed of the window order (shuffled per epoch) and of each window's stride / pseudo-action draws"""
    read_threads: int = 0
    """threads reading batches ahead (same order, same resumable state); 0 = read in the training thread"""
    window_weights: WindowWeights = WindowWeights()
    """which windows are drawn more often: those in which an object moves or the gripper acts (default: off,
    every window once)"""


@dataclasses.dataclass(frozen=True)
class ModeConfig:
    """The training modes, drawn per sample: which tokens are noisy targets (sc3_jax/model/modes.py)."""

    probs: tuple[float, float, float] = (0.8, 0.1, 0.1)
    """per-sample probabilities of forward dynamics (future frames noisy), cross-view inpainting (future frames of
    all views but one noisy; needs two views or more) and inverse dynamics (actions noisy); normalised to sum 1"""


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """Rectified-flow training: the distribution of noise levels, the loss weights, context noise."""

    t_logit_mean: float = 0.0
    """noise levels are logit-normal (SD3): t = sigmoid(t_logit_mean + t_logit_std * n). A positive mean spends
    more of the training on high noise, where a world model must actually predict from its context and actions; the
    sampler's time grid follows the same distribution"""
    t_logit_std: float = 1.0
    """spread of the logit-normal noise levels (see t_logit_mean)"""
    video_loss_weight: float = 1.0
    """weight of the video tokens' loss. Modes mix video-only and action-only losses in one batch; when their scales
    differ by 10x+ (residual video targets are small), Adam's shared second moments starve the smaller one"""
    action_loss_weight: float = 1.0
    """weight of the action tokens' loss (see video_loss_weight)"""
    context_noise_max: float = 0.0
    """anti-drift: each sample's clean context frames become (1 - s) x + s eps with s ~ U(0, context_noise_max)
    (needs model.context_noise, which gives s to the model); loss targets are never noised. 0: off"""
    self_forcing: float = 0.0
    """anti-drift: this fraction of forward-dynamics samples train on a rollout's next chunk, whose context is the
    model's own prediction (as in closed loop): training windows grow by rollout.keep_frames = l frames, one extra
    forward pass (no gradient) predicts the future of each window's first K + T frames in one Euler step from pure
    noise, and a picked sample's context becomes the last K of [real context, first l predicted frames], its targets
    the real frames after them (flow.self_forced_window). Per-frame tokenizers only. 0: off (windows as before)"""
    distill_teacher: str | None = None
    """distil the sampler (progressive distillation, Salimans & Ho 2022): a saved world model (a `sc3 train`
    workdir or an exported model) whose distill_steps-step Euler sample the trained model (the student, started
    from --train.init-from, usually the same model) learns to produce in ONE step, from the same noise and
    conditions (flow.distill_loss); it replaces the flow loss. The teacher is frozen, read again on resume, and its
    model config must match this one. None: off (the flow loss)"""
    distill_steps: int = 2
    """the teacher's Euler steps for the video targets (the student takes 1); actions (inverse dynamics, which
    the sweep re-reads in 1 step) keep the teacher's 1-step read. Read only with distill_teacher"""
    from_present: float = 0.0
    """flow from the present: a noisy future frame's flow starts not from pure noise eps but from anchor +
    from_present * eps, the anchor its view's last context frame (where that frame is clean): x_t = (1 - t) x +
    t (anchor + from_present * eps), in training (flow.loss) and in the sampler (flow.sample: rollouts,
    self-forcing, distillation). Unchanged content (a static block, the goal) then needs no drawing from noise, so
    small objects are not lost. Actions keep pure noise. Part of what the model learned: rollouts read it from the
    model's config. 0: off (pure noise)"""
    per_frame_t: bool = False
    """diffusion forcing: in training each future frame (all its views, and its action) draws its own noise level
    (logit-normal, as t_logit_mean) instead of one per sample, so the model learns futures whose frames are
    unequally noisy; sampling is unchanged (one level for all noisy tokens). One action per future token frame
    only (not the time-compressed Cosmos3 layout). False: off (one level per sample)"""
    moving_weight: float = 0.0
    """weight the video loss toward what moves: within each future frame a token's squared error weighs 1 +
    moving_weight x (its change from the same view's last clean context frame, over the frame's mean change), a
    weighted mean over the frame's tokens, so a frame's loss keeps its scale. A small object the gripper carries
    (a few tokens of a frame) then counts as much as the static table the uniform mean is dominated by. 0: off"""

    def __post_init__(self):
        if not 0.0 <= self.from_present < float("inf"):
            raise ValueError(f"flow.from_present must be a finite number >= 0 (0: off), got {self.from_present!r}")
        if not 0.0 <= self.moving_weight < float("inf"):
            raise ValueError(f"flow.moving_weight must be a finite number >= 0 (0: off), got {self.moving_weight!r}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The training run: where it writes, how long it runs, the optimiser, logging and checkpoints."""

    workdir: str = "runs/tiny"
    """run directory: config.json, norm_stats.json, checkpoints/, metrics.jsonl, tensorboard/ (and cached latents);
    rerunning with the same workdir resumes the run"""
    steps: int = 2000
    """optimizer steps to train to (a resumed run continues up to this; the learning-rate schedule follows it)"""
    lr: float = 1e-4
    """peak learning rate: linear warm-up from 0, then (train.schedule) a cosine to 0 at train.steps, or held"""
    warmup_steps: int | None = None
    """steps of linear learning-rate warm-up (None: a thirtieth of train.steps, at most 100); the rate then decays to 0 at
    train.steps, and a warm-up as long as the run is refused"""
    schedule: str = "cosine"
    """"cosine": warm up, then a cosine to 0 at train.steps (a run of known length). "wsd": warm up once, hold the
    peak (a trunk that can go on for weeks: train.steps only says where this stretch stops), and decay to 0 only from
    train.decay_start (a branch, `sc3 branch`: the copy that is measured and shipped)"""
    decay_start: int | None = None
    """schedule "wsd": the step its decay to 0 at train.steps begins (1 - sqrt, Haegele et al. 2024); None: no decay
    (the trunk holds the peak)"""
    resume_from: str | None = None
    """continue a run from its travelling state (an export with trunk_state.npz: `sc3 branch`, `scripts/trunk.sh`):
    params, optimizer moments, step, rng and data order, as the unbroken run would go on; its config must match this
    one but for what a resume may change. Ignored once this run has a checkpoint of its own (resume wins)"""
    weight_decay: float = 0.05
    """AdamW weight decay, on weight matrices only (not on norms, biases or embeddings)"""
    b1: float = 0.9
    """Adam beta1 (first-moment decay)"""
    b2: float = 0.99
    """Adam beta2 (second-moment decay)"""
    grad_clip: float = 1.0
    """global gradient-norm clipping threshold"""
    grad_accum: int = 1
    """micro-batches per step (gradient accumulation): activations of data.batch_size / grad_accum samples at a
    time, the same optimizer update as one big batch up to the per-micro-batch noise draws. `sc3 plan` says when it
    is needed"""
    init_from: str | None = None
    """start from these params instead of a random init (a `sc3 train` workdir, an exported world model or a
    `sc3 convert` output): fresh optimizer, step 0, and the source's action normalisation. Ignored once this run
    has a checkpoint of its own (resume wins)"""
    seed: int = 0
    """seed of the parameter init and of the training randomness (modes, noise levels, noise)"""
    log_every: int = 10
    """steps between writes of the metrics (metrics.jsonl, TensorBoard, the progress bar's loss)"""
    ckpt_every: int = 200
    """steps between checkpoints (the last step and a preemption are always saved)"""
    keep_checkpoints: int = 3
    """checkpoints kept in workdir/checkpoints (older ones deleted)"""
    async_checkpointing: bool = True
    """write checkpoints in the background while training goes on"""
    tensorboard: bool = True
    """also write the metrics as TensorBoard events (workdir/tensorboard)"""
    progress: bool = True
    """show progress bars (training, latent caching)"""


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    """The device mesh: how many devices each parallelism axis spans (their product is the device count)."""

    data: int = -1
    """data-parallel devices (the batch split, parameters replicated); -1: all devices not used by the other axes"""
    fsdp: int = 1
    """fully sharded data-parallel devices: the batch split, and every weight split over them too"""
    tensor: int = 1
    """tensor-parallel devices: attention heads and MLP hidden units split over them"""
    context: int = 1
    """context parallelism: the token sequence of every sample split over this many devices (needs
    model.attention_impl "context_parallel" or "ring"); 1 = no context mesh axis at all (meshes as before)"""


@dataclasses.dataclass(frozen=True)
class SampleConfig:
    """The sampler (evaluation, diagnostics and rollouts)."""

    steps: int = 10
    """Euler steps from t = 1 to t = 0 per sampler call (in a rollout: of the forward-dynamics frames)"""
    inverse_steps: int | None = None
    """Euler steps of the inverse-dynamics re-read in a rollout (None: steps). It only yields U_chunk (never the
    frames or the outcomes), and it is a third of a rollout's cost at 8 steps: fewer steps make sweeps cheaper"""
    context_noise: float = 0.0
    """noise level put on the context at inference (only read by models trained with model.context_noise)"""


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    """Closed-loop rollouts of a policy inside the world model (sc3_jax/rollout/rollout.py)."""

    policy_chunk: int = 25
    """actions proposed per policy call; at least keep_frames x (policy_hz / control_hz); one shorter than
    data.future_frames x that is held at its last action for the predicted frames the rollout discards"""
    keep_frames: int = 16
    """l: predicted frames of each chunk kept (executed, pushed into the context, averaged into U_chunk); in
    [1, data.future_frames]"""
    episode_seconds: float = 20.0
    """length of an imagined episode: episode_seconds x control_hz / keep_frames chunks (rounded up)"""
    control_hz: float = 10.0
    """the model's frame rate in a rollout (frame stride = data fps / control_hz, an integer): one model action per
    predicted frame"""
    policy_hz: float | None = None
    """the policy's action rate (None = control_hz). When higher, each group of policy_hz / control_hz raw actions
    is composed into one model-rate action (as the data pipeline composes recorded actions for strided windows)"""
    tau: float | None = None
    """termination threshold: a rollout stops at the first chunk whose U_chunk exceeds tau (in tau_units). None:
    no early termination (inf; rollout.resolve_tau). tau is in the action space's raw units, so it belongs to a
    benchmark or a calibration, never to the core: the bussing benchmark's is the paper's 0.02
    (benchmarks/bussing/hooks.py BENCHMARK_TAU, which its configs set); for another robot calibrate one on held-out
    conditions (`sc3 sweep episodes --data STORE --taus ...`, in the dataset's raw units) and pass it"""
    tau_units: str = "raw"
    """U_chunk's units, the one convention of `sc3 rollout`, `sc3 sweep` and the report: "raw" (metres / radians /
    gripper metres, the paper's units for tau = 0.02) or "normalised" (per-dimension unit variance, the model's
    units; with per-dimension stds of a few mm, U there is ~50-100x the raw value)"""


@dataclasses.dataclass(frozen=True)
class Config:
    """A world-model experiment: every setting of training, sampling and rollouts. Named configs live in
    configs/NAME.py; any field can be overridden as --SECTION.FIELD VALUE."""

    name: str = "tiny"
    """the config's name: a label (config.json, `sc3 demo`, `sc3 plan`, diagnostics); changes nothing else"""
    model: ModelConfig = ModelConfig()
    """the world model"""
    data: DataConfig = DataConfig()
    """the training data and windows"""
    modes: ModeConfig = ModeConfig()
    """the training-mode mixture"""
    flow: FlowConfig = FlowConfig()
    """rectified-flow noise levels and loss weights"""
    train: TrainConfig = TrainConfig()
    """the training run"""
    mesh: MeshConfig = MeshConfig()
    """the device mesh"""
    sample: SampleConfig = SampleConfig()
    """the sampler"""
    rollout: RolloutConfig = RolloutConfig()
    """rollouts in the world model"""


def configs_dir() -> Path:
    """The named configs: the checkout's top-level ``configs/``, installed as the package ``sc3_jax.configs``
    (pyproject's package-dir). A wheel (``pip install .``) holds them at ``sc3_jax/configs/``; an editable install's
    finder maps the name to the checkout's ``configs/``; a checkout on the path with no install (``PYTHONPATH=.``)
    has no such package, and its ``configs/`` is the folder beside ``sc3_jax/``."""
    try:
        spec = importlib.util.find_spec("sc3_jax.configs")  # locates it, runs nothing
    except ImportError:
        spec = None
    locations = spec.submodule_search_locations if spec is not None else None
    for location in locations or ():
        if Path(location).is_dir():  # (an editable finder carried to another machine may name a missing folder)
            return Path(location).resolve()
    return Path(__file__).resolve().parents[2] / "configs"


def available_configs() -> list[str]:
    return sorted(p.stem for p in configs_dir().glob("*.py") if not p.stem.startswith("_"))


def load_config(name_or_path: str) -> Config:
    """``name_or_path`` is a file path or the name of a file in ``configs/`` (``configs_dir()``), optionally followed
    by ``:ARG`` (passed to its ``get_config(arg)``, e.g. ``ablation_no_id:tiny``)."""
    name_or_path, _, arg = name_or_path.partition(":")
    path = Path(name_or_path)
    if not path.suffix:
        path = configs_dir() / f"{name_or_path}.py"
    if not path.exists():
        raise FileNotFoundError(f"no config {name_or_path!r}; named configs: {', '.join(available_configs())}")
    if path.suffix == ".json":  # a run's own config.json: re-running a run from it is what users do
        return _json_config(path)
    if path.suffix != ".py":
        raise UserError(f"--config {path}: a config is a named config, a .py file with get_config(), or a run's "
                        "config.json")
    spec = importlib.util.spec_from_file_location(f"sc3_config_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except SyntaxError as e:
        raise UserError(f"{path}:{e.lineno}: {e.msg} (a Python syntax error in the config file)") from None
    if not callable(getattr(module, "get_config", None)):
        raise UserError(f"{path}: defines no get_config(arg=None) returning a Config (see configs/tiny.py)")
    cfg = module.get_config(arg or None)
    if not isinstance(cfg, Config):
        raise UserError(f"{path}: get_config() must return sc3_jax.core.config.Config, got {type(cfg).__name__}")
    return cfg


def _json_config(path: Path) -> Config:
    """A run's config.json (``dataclasses.asdict`` of its Config) as a Config, every field's type checked."""
    from sc3_jax.core import atomic

    fix = "give a run's config.json (sc3 train writes one in its workdir), or a named config"
    raw = atomic.read_json(path, fix)
    if not isinstance(raw, dict):
        raise UserError(f"{path}: expected a run's config (a JSON object), got {type(raw).__name__}; {fix}")
    from sc3_jax.core.validate import check_config_types

    try:
        cfg = config_from_dict(raw)
    except (TypeError, ValueError, AttributeError) as e:  # a section retyped (a list where fields are)
        check_config_types(raw, Config(), str(path), fix)  # the field whose type it was, named
        raise UserError(f"{path}: does not read as a config ({e}); {fix}") from None
    check_config_types(cfg, Config(), str(path), fix)
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
        elif isinstance(cur, tuple) and isinstance(val, list):  # a string stays one (its letters are no views)
            changes[f.name] = tuple(tuple(v) if isinstance(v, list) else v for v in val)
        else:
            changes[f.name] = val
    unknown = set(d) - {f.name for f in dataclasses.fields(default)}
    if unknown:
        print(f"config.json: ignoring unknown config fields {sorted(unknown)}", file=sys.stderr)
    return dataclasses.replace(default, **changes)
