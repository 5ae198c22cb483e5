"""Video <-> tokens. One interface: the pixel-patch tokenizer (exact, no time compression), the learned
convolutional autoencoder (``model/autoencoder.py``, per frame, trained with ``sc3 train-tokenizer``) and the Wan VAE
(``model/wan_vae.py``; 4x causal time compression: ``latent_frames(F) = 1 + (F - 1) // 4``). Training and rollouts
read the token-frame counts of a (context, future) window off ``window_tokens``.

Patch order is (row, col) over the frame with features ordered (pi, pj, c), as Cosmos3 patchifies latents."""
from __future__ import annotations

import dataclasses
import functools
from typing import Protocol

import jax
import jax.numpy as jnp


class Tokenizer(Protocol):
    def grid(self, image_size: tuple[int, int]) -> tuple[int, int]: ...  # tokens per frame as (rows, cols)

    @property
    def token_dim(self) -> int: ...

    def encode(self, frames: jax.Array) -> jax.Array: ...  # uint8 [..., F, H, W, 3] -> [..., F, P, D]

    def decode(self, tokens: jax.Array, image_size: tuple[int, int]) -> jax.Array: ...  # -> float [-1, 1]

    @property
    def time_compression(self) -> int: ...  # frames per token frame (after the first)

    def latent_frames(self, num_frames: int) -> int: ...  # token frames that num_frames frames encode to


def to_unit(frames: jax.Array) -> jax.Array:
    """uint8 [0, 255] -> float32 [-1, 1]."""
    return frames.astype(jnp.float32) / 127.5 - 1.0


def to_uint8(x: jax.Array) -> jax.Array:
    """float [-1, 1] -> uint8, rounding (exact inverse of ``to_unit`` on its image)."""
    return jnp.clip(jnp.round((x + 1.0) * 127.5), 0, 255).astype(jnp.uint8)


@dataclasses.dataclass(frozen=True)
class PixelPatchTokenizer:
    patch_size: int = 4
    channels: int = 3

    def grid(self, image_size):
        h, w = image_size
        if h % self.patch_size or w % self.patch_size:
            raise ValueError(f"image size {image_size} is not a multiple of patch size {self.patch_size}")
        return h // self.patch_size, w // self.patch_size

    @property
    def token_dim(self) -> int:
        return self.patch_size * self.patch_size * self.channels

    @property
    def time_compression(self) -> int:
        return 1

    def latent_frames(self, num_frames: int) -> int:
        return num_frames

    def encode(self, frames):
        x = to_unit(frames) if frames.dtype == jnp.uint8 else frames
        *lead, h, w, c = x.shape
        p = self.patch_size
        rows, cols = self.grid((h, w))
        x = x.reshape(*lead, rows, p, cols, p, c)
        x = jnp.moveaxis(x, -4, -3)  # [..., rows, cols, p, p, c]
        return x.reshape(*lead, rows * cols, p * p * c)

    def decode(self, tokens, image_size):
        *lead, n, d = tokens.shape
        p = self.patch_size
        rows, cols = self.grid(image_size)
        x = tokens.reshape(*lead, rows, cols, p, p, self.channels)
        x = jnp.moveaxis(x, -3, -4)  # [..., rows, p, cols, p, c]
        return x.reshape(*lead, rows * p, cols * p, self.channels)


@dataclasses.dataclass(frozen=True, eq=False)
class ConvAETokenizer:
    """The learned per-frame autoencoder: frames -> standardised latents [h, w, C] -> ``patch_size`` x
    ``patch_size`` latent patches as tokens. Training reads latents cached once per dataset (``data/latent_cache.py``)
    and only patchifies them (``from_latents``), so the encoder never runs inside the train step."""
    path: str
    patch_size: int = 4

    def __post_init__(self):
        from sc3_jax.model import autoencoder as ae
        cfg, image_size, params, stats = ae.load(self.path)
        for k, v in (("cfg", cfg), ("image_size", image_size), ("params", params), ("stats", stats)):
            object.__setattr__(self, k, v)

    def __hash__(self):  # jit caches key on the tokenizer through the model config (path, patch): same weights
        return hash((self.path, self.patch_size))

    def __eq__(self, other):
        return isinstance(other, ConvAETokenizer) and (self.path, self.patch_size) == (other.path, other.patch_size)

    def latent_size(self, image_size) -> tuple[int, int]:
        if tuple(image_size) != tuple(self.image_size):
            raise ValueError(f"tokenizer {self.path} was trained on {tuple(self.image_size)} images, got {image_size}")
        f = self.cfg.downsample
        return image_size[0] // f, image_size[1] // f

    def grid(self, image_size):
        h, w = self.latent_size(image_size)
        if h % self.patch_size or w % self.patch_size:
            raise ValueError(f"latent size {(h, w)} is not a multiple of patch size {self.patch_size}")
        return h // self.patch_size, w // self.patch_size

    @property
    def token_dim(self) -> int:
        return self.patch_size * self.patch_size * self.cfg.latent_channels

    @property
    def time_compression(self) -> int:
        return 1

    def latent_frames(self, num_frames: int) -> int:
        return num_frames

    def encode_latents(self, frames):
        """uint8 [..., H, W, 3] -> standardised latents [..., h, w, C]."""
        from sc3_jax.model import autoencoder as ae
        return ae.encode(self.params, self.stats, frames)

    def from_latents(self, latents):
        """Latents [..., h, w, C] -> tokens [..., P, p*p*C] (a reshape)."""
        return PixelPatchTokenizer(self.patch_size, self.cfg.latent_channels).encode(latents.astype(jnp.float32))

    def encode(self, frames):
        return self.from_latents(self.encode_latents(frames))

    def decode(self, tokens, image_size):
        from sc3_jax.model import autoencoder as ae
        latents = PixelPatchTokenizer(self.patch_size, self.cfg.latent_channels).decode(
            tokens, self.latent_size(image_size))
        return ae.decode(self.params, self.stats, latents)


def window_tokens(tok: Tokenizer, context: int, future: int) -> tuple[int, int]:
    """(context, future) token frames of a window of ``context`` then ``future`` frames. A causal tokenizer with
    c x time compression encodes frame 0 alone and every later c frames as one token frame, so the window must be
    1 + c k context and c t future frames (k + 1 and t token frames): then the context's tokens do not depend on
    the future and the future's are whole token frames."""
    c = tok.time_compression
    if c > 1 and ((context - 1) % c or future % c or context < 1):
        raise ValueError(f"a tokenizer with {c}x time compression needs context_frames = 1 + {c} k and "
                         f"future_frames = {c} t frames, got {context} and {future}")
    k = tok.latent_frames(context)
    return k, tok.latent_frames(context + future) - k


def make_tokenizer(model_cfg) -> Tokenizer:
    if model_cfg.tokenizer == "pixel":
        return PixelPatchTokenizer(model_cfg.patch_size, model_cfg.channels)
    if model_cfg.tokenizer == "conv_ae":
        if not model_cfg.tokenizer_path:
            raise ValueError("tokenizer 'conv_ae' needs model.tokenizer_path (a `sc3 train-tokenizer` output)")
        return _conv_ae(model_cfg.tokenizer_path, model_cfg.patch_size)
    if model_cfg.tokenizer in ("wan2.1", "wan2.2"):
        from sc3_jax.model.wan_tokenizer import make_wan_tokenizer  # lazy: the VAE module is large and optional

        return make_wan_tokenizer(model_cfg.tokenizer, model_cfg.tokenizer_path, patch_size=model_cfg.patch_size)
    raise ValueError(f"unknown tokenizer {model_cfg.tokenizer!r} (available: 'pixel', 'conv_ae', 'wan2.1', 'wan2.2')")


@functools.lru_cache(maxsize=8)
def _conv_ae(path: str, patch_size: int) -> ConvAETokenizer:
    return ConvAETokenizer(path, patch_size)  # weights load once per (path, patch)


# ----------------------------------------------------------------------------------------------------------------
# A config's token geometry (its tokenizer on its image size and window): the one place these counts are made
# ----------------------------------------------------------------------------------------------------------------
def token_geometry(cfg) -> tuple[int, tuple[int, int]]:
    """(token_dim, (rows, cols) tokens per frame) of a ``Config``'s tokenizer and image size."""
    tok = make_tokenizer(cfg.model)
    return tok.token_dim, tok.grid(cfg.data.image_size)


def context_token_frames(cfg) -> int | None:
    """Context *token* frames when the tokenizer compresses time (None: one token frame per frame, K = F - T).
    A window of 1 + 4 k context and 4 t future frames is k + 1 context and t future token frames with 4 t actions
    (``window_tokens``): the Cosmos3 layout (actions independent of frames); the sc3 layout needs one action per
    token frame."""
    tok = make_tokenizer(cfg.model)
    if tok.time_compression == 1:
        return None
    k, _ = window_tokens(tok, cfg.data.context_frames, cfg.data.future_frames)
    if cfg.model.layout != "cosmos3":
        raise ValueError(f"{tok.time_compression}x time-compressed tokens need model.layout='cosmos3' (several "
                         "actions per token frame); the sc3 layout has one action per future frame")
    return k


def tokens_per_sample(cfg) -> int:
    """Tokens of one training sample: every view's token frames of the window (fewer than its frames when the
    tokenizer compresses time) times the tokens per frame, plus one token per action (one per future frame)."""
    tok = make_tokenizer(cfg.model)
    d = cfg.data
    rows, cols = tok.grid(d.image_size)
    k, t = window_tokens(tok, d.context_frames, d.future_frames)
    return len(d.views) * (k + t) * rows * cols + d.future_frames
