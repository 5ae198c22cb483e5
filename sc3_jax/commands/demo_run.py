"""The pieces of `sc3 demo` (``commands/demo.py``): train on the synthetic multi-view environment's episodes, then
check forward dynamics, action use, inverse dynamics and inpainting on held-out episodes against the baselines each
must beat (sc3_jax/evaluation/world_model.py), each with a verdict."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from sc3_jax.core.config import Config


def with_data_facts(cfg: Config) -> Config:
    """``cfg`` with its store's frame rate and recorded state size (``cfg.data.path``'s dataset.json), as `sc3 train`
    records them (data/shape.py), so the model a demo makes reads them back (``checkpoint.read_robot``). A demo
    workdir started before demos recorded them resumes as it was saved (its config.json without them: a changed
    config would be refused)."""
    from sc3_jax.core import atomic
    from sc3_jax.data.episodes import EpisodeStore

    saved = Path(cfg.train.workdir) / "config.json"
    old = atomic.read_json(saved, "restore it, or use another --out") if saved.is_file() else None
    if isinstance(old, dict) and isinstance(old.get("data"), dict) and old["data"].get("fps") is None:
        return cfg
    store = EpisodeStore(cfg.data.path)
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, fps=float(store.fps),
                                                             state_dim=int(store.state_dim or 0)))


def heldout_batches(cfg: Config, path: str, num_batches: int, batch_size: int = 16):
    """Deterministic held-out windows: stride 1, recorded actions (no pseudo-actions), the training stats."""
    from sc3_jax.model import checkpoint
    from sc3_jax.data import pipeline
    from sc3_jax.data.episodes import EpisodeStore

    stats = checkpoint.read_norm_stats(cfg.train.workdir)
    dcfg = dataclasses.replace(cfg.data, path=path, strides=(1,), pseudo_action_prob=0.0, batch_size=batch_size,
                               seed=1234)
    it = pipeline.make_iterator(dcfg, EpisodeStore(path), stats)
    return [next(it) for _ in range(num_batches)]


def train_and_evaluate(cfg: Config, heldout: str, eval_batches: int = 4) -> dict:
    from sc3_jax.model import checkpoint
    from sc3_jax.train import train
    from sc3_jax.evaluation import world_model

    train.train(cfg)
    params = checkpoint.load_params(cfg.train.workdir, cfg)
    return world_model.evaluate(params, cfg, heldout_batches(cfg, heldout, eval_batches))


@dataclasses.dataclass(frozen=True)
class Verdict:
    """One held-out check: the model's number against its baseline's, and whether it beats it by the margin."""

    check: str
    value: str
    baseline: str
    need: str
    passed: bool

    def line(self) -> str:
        return f"{self.check:17s}: {self.value} vs {self.baseline} (needs {self.need}): " \
               f"{'PASS' if self.passed else 'FAIL'}"


# The margins tests/test_learning.py asserts after 1,200 steps: a model that merely ties its baseline has not learned.
PSNR_MARGIN_DB = {"fd_psnr/copy_last_psnr": 0.5, "fd_psnr/fd_shuffled_psnr": 0.5, "cvi_psnr/mean_frame_psnr": 1.0}
ID_MSE_RATIO = 0.7


def verdicts(m: dict[str, float]) -> list[Verdict]:
    """Each check of ``world_model.evaluate``'s metrics ``m`` against its baseline; a NaN fails."""
    def psnr(check, key, base, name):
        margin = PSNR_MARGIN_DB[f"{key}/{base}"]
        return Verdict(check, f"PSNR {m[key]:.2f} dB", f"{name} {m[base]:.2f} dB", f"+{margin:g} dB",
                       math.isfinite(m[key]) and m[key] > m[base] + margin)

    return [psnr("forward dynamics", "fd_psnr", "copy_last_psnr", "repeat-last-frame"),
            psnr("uses its actions", "fd_psnr", "fd_shuffled_psnr", "shuffled actions"),
            Verdict("inverse dynamics", f"action MSE {m['id_mse']:.3f} (sampled {m['id_sample_mse']:.3f})",
                    f"mean action {m['mean_action_mse']:.3f}",
                    f"< {ID_MSE_RATIO:g}x", math.isfinite(m["id_mse"]) and m["id_mse"] < ID_MSE_RATIO *
                    m["mean_action_mse"]),
            psnr("inpainting", "cvi_psnr", "mean_frame_psnr", "mean frame")]
