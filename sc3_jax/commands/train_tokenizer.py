"""``sc3 train-tokenizer --data STORE --workdir DIR [--heldout STORE] [--ae.FIELD VALUE ...]``: the learned latent
tokenizer (conv autoencoder, ``sc3_jax/tokenizer_train.py``)."""
from __future__ import annotations

import dataclasses
from typing import Annotated

import tyro

from sc3_jax.commands import parse
from sc3_jax.tokenizer_config import AEConfig, TokenizerTrainConfig

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
    from sc3_jax import tokenizer_train as tt

    cfg = TokenizerTrainConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(TokenizerTrainConfig)})
    ae_cfg = a.ae
    result = tt.export_latest(cfg, ae_cfg) if a.export_only else tt.train(cfg, ae_cfg)
    print("\n".join(summary(cfg, result)))
    return 0


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
