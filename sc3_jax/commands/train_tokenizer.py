"""``sc3 train-tokenizer --data STORE --workdir DIR [--heldout STORE] [--ae.FIELD VALUE ...]``: the learned latent
tokenizer (conv autoencoder, ``sc3_jax/train/tokenizer_train.py``)."""
from __future__ import annotations

import dataclasses
from typing import Annotated

import tyro

from sc3_jax.commands import parse
from sc3_jax.core.tokenizer_config import AEConfig, TokenizerTrainConfig

SUMMARY = "train the learned latent tokenizer (a conv autoencoder)"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args(TokenizerTrainConfig):
    """Train (or resume: rerun the same command) the convolutional autoencoder on single-view frames of an episode
    store, then write WORKDIR/tokenizer (the directory model.tokenizer_path points at) and, with --heldout, its
    reconstruction PSNR on held-out episodes against a static baseline (WORKDIR/tokenizer/eval.json)."""

    # the field TokenizerTrainConfig names batch_size, spelt as every command spells a batch (commands/flags.py)
    batch_size: Annotated[int, tyro.conf.arg(name="batch")] = TokenizerTrainConfig.batch_size
    """single-view images per step"""

    ae: AEConfig = AEConfig()
    """the autoencoder's architecture"""
    export_only: bool = False
    """only write WORKDIR/tokenizer (and its evaluation) from the latest checkpoint"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "train-tokenizer")  # an architecture AEConfig refuses is tyro's usage error
    from sc3_jax.train import tokenizer_train as tt

    cfg = TokenizerTrainConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(TokenizerTrainConfig)})
    check_options(cfg)
    ae_cfg = a.ae
    result = tt.export_latest(cfg, ae_cfg) if a.export_only else tt.train(cfg, ae_cfg)
    print("\n".join(summary(cfg, result)))
    return 0


# the numeric options at the door: (field, option, low, high, what); --steps 0 or --lr nan exited 0 with an
# untrained tokenizer, --batch 0 was a traceback from numpy, --steps 1e10 trained for ever
BOUNDS = [("steps", "--steps", 1, 10**9, "optimizer steps"), ("batch_size", "--batch", 1, 1_000_000, "images per step"),
          ("lr", "--lr", 1e-12, 10, "a learning rate"), ("warmup_steps", "--warmup-steps", 0, 10**9, "steps"),
          ("moving_weight", "--moving-weight", 0, 1e6, "a loss weight"),
          ("moving_threshold", "--moving-threshold", 0, 1, "a fraction of the pixel range"),
          ("seed", "--seed", 0, 2**32 - 1, "a seed"), ("ckpt_every", "--ckpt-every", 1, 10**9, "steps"),
          ("eval_frames", "--eval-frames", 1, 10**6, "held-out images per view")]


def check_options(cfg) -> None:
    """One line for an option out of its range, or a --workdir that is a file, under one or a link, before any
    data is read."""
    from sc3_jax.core.validate import in_range, out_dir

    for field, option, low, high, what in BOUNDS:
        in_range(option, getattr(cfg, field), low, high, what)
    out_dir(cfg.workdir, "--workdir")


def summary(cfg, result: dict) -> list[str]:
    """What was written where, and the held-out PSNRs against the static baseline."""
    out = f"{cfg.workdir}/tokenizer"
    h, w, c = result["latent"]
    lines = [f"tokenizer: {out} ({result['params'] / 1e6:.2f}M parameters; latents {h}x{w}x{c} per view and frame); "
             f"a world model reads it with --model.tokenizer conv_ae --model.tokenizer-path {out}",
             f"training log: {cfg.workdir}/metrics.jsonl (loss, training PSNR every 25 steps)"]
    if "heldout" not in result:
        return lines + ["no held-out evaluation: pass --heldout STORE (episodes not trained on) to measure the "
                        "reconstruction PSNR"]
    lines += [f"held-out reconstruction on {cfg.heldout} ({cfg.eval_frames} images per view; {out}/eval.json), PSNR "
              "in dB, higher is better. static = the episode's temporal median frame of the view: what a tokenizer "
              "that drops everything that moves would score; moving pixels are the arm and the objects, what the "
              "world model exists to render:",
              "| view | whole frame | static | moving pixels | static | moving fraction |", "|---|---|---|---|---|---|"]
    for view, r in result["heldout"].items():
        lines.append(f"| {view} | {r['psnr']:.1f} | {r['static_psnr']:.1f} | {r['psnr_moving']:.1f} | "
                     f"{r['static_psnr_moving']:.1f} | {r['moving_fraction']:.1%} |")
    return lines
