"""The library side of ``sc3 sim demos`` and ``sc3 sim eval`` (the command itself: ``commands/sim.py`` beside it):
scripted-expert demonstrations from plain arguments, and a policy evaluated by any of its spellings. It stands apart
from the simulator's modules because ``eval`` resolves policy names (``policies/resolve.py``), which they must not
import.
"""
from __future__ import annotations


def demos(out: str, episodes: int = 100, seed: int = 0, grasp_noise: float = 0.0, release_noise: float = 0.0,
          wrong_destination_prob: float = 0.0, action_noise: float = 0.0, image_size: tuple[int, int] = (64, 64),
          control_hz: int = 20, n_objects: int = 3, progress: bool = True, policy: str | None = None,
          allow_swap_all: bool = False) -> dict:
    from .demos import generate_demos
    from .expert import ExpertKnobs
    knobs = ExpertKnobs(grasp_noise, release_noise, wrong_destination_prob, action_noise,
                        never_swap_all=not allow_swap_all)
    return generate_demos(out, episodes, seed, knobs, tuple(image_size), control_hz, n_objects, progress=progress,
                          policy=policy)


def eval(policy: str, task: str = "bussing", episodes: int = 36, out: str | None = None, videos: bool = True,
         image_size: tuple[int, int] = (64, 64), progress: bool = True) -> dict:  # noqa: A001 (CLI verb)
    from sc3_jax.core.errors import UserError
    from sc3_jax.policies.resolve import resolve  # any spelling; a command may import above the simulator
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    from .policy_eval import evaluate_policy
    try:
        resolved = resolve(policy, named=named_policy)
    except ValueError as e:  # a misspelt name: the message lists the spellings and the zoo
        raise UserError(f"--policy: {e}") from None
    return evaluate_policy(resolved.policy, task, episodes, out, image_size=tuple(image_size), videos=videos,
                           progress=progress)
