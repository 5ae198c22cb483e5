"""The project's ``Tokenizer`` protocol (``tokenizer.py``) over a Wan VAE (``wan_vae.py``; pretrained weights read
by ``wan_vae_convert.py``): frames -> normalised latents -> latent-patch tokens."""
from __future__ import annotations

import dataclasses
import functools
import warnings

import jax

from sc3_jax.model import wan_vae
from sc3_jax.model.wan_vae_convert import load_diffusers


@dataclasses.dataclass(frozen=True, eq=False)
class WanTokenizer:
    """The Tokenizer protocol over a Wan VAE: frames -> normalised latents -> (p x p latent patch) tokens.

    Time is compressed: ``F`` frames give ``latent_frames(F) = 1 + (F - 1) // 4`` token frames and ``f`` token
    frames decode to ``1 + 4 (f - 1)`` frames. ``encode``/``decode`` use the held ``params``; inside your own
    ``jax.jit`` prefer ``encode_with``/``decode_with`` so the weights are traced arguments, not constants."""
    cfg: wan_vae.WanVAEConfig
    params: dict
    patch_size: int = 1  # latent patch (Cosmos3 uses 2)
    batch_size: int | None = None  # encode/decode this many videos at a time (lax.map); None = all at once

    @property
    def time_compression(self) -> int:
        return self.cfg.temporal_ratio

    def latent_frames(self, num_frames: int) -> int:
        return self.cfg.latent_frames(num_frames)

    def pixel_frames(self, num_latent_frames: int) -> int:
        return self.cfg.pixel_frames(num_latent_frames)

    def latent_size(self, image_size):
        h, w = image_size
        r = self.cfg.spatial_ratio
        if h % r or w % r:
            raise ValueError(f"image size {image_size} is not a multiple of the VAE's spatial ratio {r}")
        return h // r, w // r

    def grid(self, image_size):
        h, w = self.latent_size(image_size)
        p = self.patch_size
        return -(-h // p), -(-w // p)

    @property
    def token_dim(self) -> int:
        return self.patch_size * self.patch_size * self.cfg.z_dim

    def encode_with(self, params, frames):
        self.latent_size(frames.shape[-3:-1])
        return wan_vae.encode_tokens(params, self.cfg, frames, self.patch_size, self.batch_size)

    def decode_with(self, params, tokens, image_size, clamp: bool = True):
        self.latent_size(image_size)
        return wan_vae.decode_tokens(params, self.cfg, tokens, tuple(image_size), self.patch_size, self.batch_size,
                                     clamp)

    def encode(self, frames):
        return self.encode_with(self.params, frames)

    def decode(self, tokens, image_size):
        return self.decode_with(self.params, tokens, image_size)

    # ---- constructors ----
    @classmethod
    def from_pretrained(cls, path, patch_size: int = 1, batch_size: int | None = None, **cfg_overrides):
        """A diffusers ``AutoencoderKLWan`` directory (config.json + safetensors)."""
        cfg, params = load_diffusers(path, **cfg_overrides)
        return cls(cfg, params, patch_size, batch_size)

    @classmethod
    def random(cls, cfg: wan_vae.WanVAEConfig, seed: int = 0, patch_size: int = 1, batch_size: int | None = None):
        return cls(cfg, wan_vae.init_params(cfg, jax.random.key(seed)), patch_size, batch_size)


def make_wan_tokenizer(name: str, path: str | None = None, patch_size: int = 1, batch_size: int | None = None,
                       seed: int = 0, **cfg_overrides) -> WanTokenizer:
    """``name`` in PRESETS ("wan2.1", "wan2.2"). With ``path`` (a diffusers VAE directory) the weights and config
    come from it (and must be of that variant); without, randomly initialised weights of the preset architecture
    (for plumbing and tests -- a real tokenizer needs the pretrained weights; a warning says so). Cached: repeated
    calls with the same arguments return the same tokenizer (weights loaded once)."""
    if name not in wan_vae.PRESETS:
        raise ValueError(f"unknown Wan VAE {name!r} (available: {sorted(wan_vae.PRESETS)})")
    return _make_wan_tokenizer(name, path, patch_size, batch_size, seed, **cfg_overrides)


@functools.lru_cache(maxsize=4)
def _make_wan_tokenizer(name, path, patch_size, batch_size, seed, **cfg_overrides):
    if path is None:
        warnings.warn(f"{name} tokenizer with randomly initialised weights (no checkpoint path given)", stacklevel=3)
        return WanTokenizer.random(wan_vae.PRESETS[name](**cfg_overrides), seed, patch_size, batch_size)
    tok = WanTokenizer.from_pretrained(path, patch_size, batch_size, **cfg_overrides)
    if tok.cfg.is_residual != (name == "wan2.2"):
        raise ValueError(f"{path} holds a {'wan2.2' if tok.cfg.is_residual else 'wan2.1'}-style VAE, not {name}")
    return tok
