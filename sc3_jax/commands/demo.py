"""``sc3 demo [--out runs/demo] [--steps N]``: the whole training side on a CPU in minutes, ending with a verdict per
held-out check (sc3_jax/commands/demo_run.py)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from sc3_jax.commands import parse_with_config
from sc3_jax.commands.flags import onto_config

SUMMARY = "generate synthetic multi-view data, train the tiny model, say how far it got"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Generate the synthetic multi-view environment's episodes, train the tiny config on them, then check forward
    dynamics, action use, inverse dynamics and inpainting on held-out episodes against the baseline each must beat:
    a PASS / FAIL per check. Resumes if interrupted (rerun the same command). Any --SECTION.FIELD VALUE of `sc3 train
    --help-config` overrides the config, e.g. --train.lr 1e-3."""

    out: str = "runs/demo"
    """where the episodes, the training run (checkpoints) and demo_metrics.json go"""
    config: str = "tiny"
    """a named config (`sc3 configs`) or a config file"""
    steps: int | None = None
    """training steps (None: the config's train.steps)"""
    episodes: int = 200
    """synthetic training episodes (16 more are held out)"""
    batch: int | None = None
    """global batch (the config's data.batch_size; None: the config's)"""


def _config(a: Args):
    from sc3_jax.core.config import load_config, replace

    base = load_config(a.config)
    out = Path(a.out)
    return replace(onto_config(base, str(out / "episodes"), a.batch),
                   train=dict(workdir=str(out / "train"), steps=a.steps or base.train.steps))


def main(argv: list[str]) -> int:
    a, cfg = parse_with_config(Args, argv, "demo", _config)
    from sc3_jax.core import atomic
    from sc3_jax.commands import demo_run as demo
    from sc3_jax.data import synthetic

    from sc3_jax.core.validate import in_range, out_dir

    in_range("--episodes", a.episodes, 1, 1_000_000, "synthetic training episodes")
    if a.steps is not None:  # 0 fell back to the config's 1,500 steps without a word
        in_range("--steps", a.steps, 1, 10**9, "optimizer steps")
    out_dir(a.out, "--out")  # a file there, under one or a link: one line before anything is generated
    out, heldout = Path(a.out), Path(a.out) / "heldout"
    print(f"[1/3] synthetic episodes: {a.episodes} -> {cfg.data.path}, 16 held out -> {heldout}")
    synthetic.generate(cfg.data.path, a.episodes, image_size=cfg.data.image_size, seed=0)
    synthetic.generate(str(heldout), 16, image_size=cfg.data.image_size, seed=10_000)
    cfg = demo.with_data_facts(cfg)  # the model it makes records its data's frame rate (checkpoint.read_robot)
    print(f"[2/3] training {cfg.name} for {cfg.train.steps} steps -> {cfg.train.workdir} (resumes if interrupted)")
    metrics = demo.train_and_evaluate(cfg, str(heldout))
    atomic.write_json(out / "demo_metrics.json", metrics)
    print("[3/3] held-out checks, each against the baseline it must beat")
    verdicts = demo.verdicts(metrics)
    print("\n".join(v.line() for v in verdicts))
    passed = sum(v.passed for v in verdicts)
    print(f"{passed}/{len(verdicts)} checks pass"
          + ("" if passed == len(verdicts) else " (a short run may not have learned yet: try more --steps)"))
    print(f"outputs: metrics {out / 'demo_metrics.json'}, checkpoints {cfg.train.workdir}, episodes {cfg.data.path} "
          f"and {heldout}")
    return 0
