"""The shape check: the config's views, image size, window, action dimension and tokenizer, refused in one line
naming the field before anything is traced (``check_shape``); the robot a chunk is costed for (``cost_robot``)."""
from __future__ import annotations

from sc3_jax.core.errors import UserError
from sc3_jax.train.config_flag import config_flag
from sc3_jax.train.plan_vae import WAN, vae_config


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
