"""The learned latent tokenizer's settings: its architecture (``AEConfig``, ``model/autoencoder.py``) and its
training (``TokenizerTrainConfig``, ``tokenizer_train.py``). Apart from the code that uses them and free of jax, so
that ``sc3 train-tokenizer --help`` (whose options these are) loads nothing heavy."""
from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class AEConfig:
    """The autoencoder's architecture; a workdir keeps the one it was started with."""

    latent_channels: int = 16
    """channels of the latent at each latent position"""
    downsample: int = 4
    """latent positions are downsample x downsample pixels; a power of two >= 2 dividing the image size (each
    factor of two is one strided convolution of the encoder and one upsampling of the decoder)"""
    width: int = 128
    """channels at the latent resolution"""
    mid_width: int = 64
    """channels at every intermediate resolution (between the full-resolution convolution and the latent
    resolution)"""
    out_width: int = 32
    """channels of the last full-resolution convolution"""
    blocks: int = 2
    """residual blocks at the latent resolution (encoder and decoder each)"""

    def __post_init__(self):
        if self.downsample < 2 or self.downsample & (self.downsample - 1):
            raise ValueError(f"downsample must be a power of two >= 2, got {self.downsample}")

    @property
    def levels(self) -> int:
        return int(math.log2(self.downsample))


@dataclasses.dataclass(frozen=True)
class TokenizerTrainConfig:
    """How the tokenizer is trained and evaluated."""

    data: str | None = None
    """the training episode store (required: no robot's store is a default)"""
    heldout: str | None = None
    """a separate episode store for the held-out evaluation (None: no evaluation)"""
    workdir: str = "runs/tokenizer"
    """checkpoints, metrics.jsonl and the exported tokenizer (WORKDIR/tokenizer)"""
    views: tuple[str, ...] | None = None
    """the camera views trained on (all share one autoencoder; None: every view of --data)"""
    steps: int = 3000
    """training steps"""
    batch_size: int = 32
    """single-view images per step"""
    lr: float = 2e-3
    """peak learning rate (warmup, then cosine decay to 5% of it)"""
    warmup_steps: int = 100
    """steps of linear learning-rate warmup"""
    moving_weight: float = 4.0
    """extra loss weight of moving pixels (those that differ from the episode's temporal median: the arm, the
    objects): weight 1 + moving_weight"""
    moving_threshold: float = 0.06
    """|pixel - temporal median| in [-1, 1] units (any channel) to count as moving"""
    seed: int = 0
    """initialisation and batch seed (batch i is a function of (seed, i): a resumed run sees the same batches)"""
    ckpt_every: int = 250
    """checkpoint every this many steps (and at the end)"""
    eval_frames: int = 256
    """held-out images per view for the evaluation"""
    progress: bool = True
    """show a progress bar"""
