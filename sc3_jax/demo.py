"""`sc3 demo`: the whole training side on a CPU in minutes. Generates the synthetic multi-view environment's
episodes, trains the tiny config, then checks forward dynamics, action use, inverse dynamics and inpainting on
held-out episodes against the baselines each must beat (sc3_jax/evaluate/world_model.py)."""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from sc3_jax.config import Config, load_config, replace


def heldout_batches(cfg: Config, path: str, num_batches: int, batch_size: int = 16):
    """Deterministic held-out windows: stride 1, recorded actions (no pseudo-actions), the training stats."""
    from sc3_jax import checkpoint
    from sc3_jax.data import pipeline
    from sc3_jax.data.episodes import EpisodeStore

    stats = checkpoint.read_norm_stats(cfg.train.workdir)
    dcfg = dataclasses.replace(cfg.data, path=path, strides=(1,), pseudo_action_prob=0.0, batch_size=batch_size,
                               seed=1234)
    it = pipeline.make_iterator(dcfg, EpisodeStore(path), stats)
    return [next(it) for _ in range(num_batches)]


def train_and_evaluate(cfg: Config, heldout: str, eval_batches: int = 4) -> dict:
    from sc3_jax import checkpoint, train
    from sc3_jax.evaluate import world_model

    train.train(cfg)
    params = checkpoint.load_params(cfg.train.workdir, cfg)
    return world_model.evaluate(params, cfg, heldout_batches(cfg, heldout, eval_batches))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="sc3 demo", description=__doc__)
    ap.add_argument("--out", default="runs/demo", help="where data, checkpoints and metrics go")
    ap.add_argument("--config", default="tiny")
    ap.add_argument("--steps", type=int, default=None, help="training steps (default: the config's)")
    ap.add_argument("--episodes", type=int, default=200)
    args = ap.parse_args(argv)

    from sc3_jax.data import synthetic
    from sc3_jax.evaluate import world_model

    out = Path(args.out)
    base = load_config(args.config)
    cfg = replace(base, data=dict(path=str(out / "episodes")),
                  train=dict(workdir=str(out / "train"), steps=args.steps or base.train.steps))
    print(f"[1/3] synthetic episodes -> {out}")
    synthetic.generate(cfg.data.path, args.episodes, image_size=cfg.data.image_size, seed=0)
    synthetic.generate(str(out / "heldout"), 16, image_size=cfg.data.image_size, seed=10_000)
    print(f"[2/3] training {cfg.name} for {cfg.train.steps} steps -> {cfg.train.workdir} (resumes if interrupted)")
    metrics = train_and_evaluate(cfg, str(out / "heldout"))
    print("[3/3] held-out checks")
    print(world_model.summary(metrics))
    (out / "demo_metrics.json").write_text(json.dumps(metrics, indent=1))
    return 0
