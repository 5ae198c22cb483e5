"""``sc3 train-state --world-model WM [--data STORE] [--steps N ...]``: the learned robot state of a world model
(``sc3_jax/rollout/state_head.py``): what the robot's sensors would read inside its imagined rollouts, for the policies
that act there. ``sc3 train`` runs it after training on a store that records a state; run it for a world model
trained before, or on more data of the same robot."""
from __future__ import annotations

import dataclasses

from sc3_jax.commands import parse
from sc3_jax.rollout.state_head import FitConfig

SUMMARY = "train the learned robot state a world model hands its policies"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True, kw_only=True)
class Args(FitConfig):
    """Train the learned robot state of a saved world model on the episodes of its robot (holding out a tenth of
    them for the figures) and save it as WM/state_head.npz (--world-model WM)."""

    world_model: str
    """a `sc3 train` workdir or an exported world model"""
    data: str | None = None
    """an episode store of the same robot that records its state (None: the world model's data.path)"""
    progress: bool = True
    """a progress bar on stderr (--no-progress: none, for batch logs)"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "train-state")
    fit = FitConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(FitConfig)})
    print(describe(*train(a.world_model, a.data, fit, a.progress)))
    return 0


def train(world_model: str, data: str | None, fit: FitConfig, progress: bool):
    from sc3_jax.rollout import state_head
    return state_head.train_for(world_model, data, fit, progress)


def describe(path, info: dict) -> str:
    """One line: where the head is, what it read, how well it follows held-out episodes."""
    e, h = info["episodes"], info["heldout"]
    said = (f"held-out RMS error {h['head']:.3f} per state dimension (in units of its spread) against {h['hold']:.3f} "
            "for holding the first state" if h else "no held-out episode (one episode in the store)")
    return (f"learned state: {path} ({len(info['state_names'])}-D: {', '.join(info['state_names'])}; "
            f"{e['train']} training episodes of {info['store']}); {said}")
