"""The SO-101 simulator as a gymnasium vector env with lerobot-eval's raw keys, on the sweep's initial conditions:
``lerobot-eval --env.type=sc3_so101`` (plugins/lerobot_env_sc3) gives a LeRobot policy trained on our collected data
its *real* success rate, on the cameras it was trained on (the simulator's own ``--env.type=so101`` renders only its
``front`` room camera).

    env = vec_env(num_envs=2)                     # SyncVectorEnv of So101GymEnv, SAME_STEP autoreset
    obs, info = env.reset(seed=0)                 # the sweep's conditions 0 and 1
    obs, reward, terminated, truncated, info = env.step(actions)   # float32 [2, 4]: dx, dy, dz, gripper

Seeds are the sweep's conditions: ``reset(seed=s)`` resets the simulator at seed ``EVAL_SEED0 + s`` (20,000,000 + s,
as ``sc3 sweep so101`` and ``sc3 so101 zoo-eval``: neither a collected training nor a held-out episode) and applies
``HOLD_STEPS`` of ``HOLD`` (gripper open, no motion: the step that gives the world model its second context frame), so
``lerobot-eval --seed=0``'s episode i starts where the sweep's condition i (its initial_conditions store's
``seed<20000000+i>``) and that condition's real episode start. The vector env's ``reset(seed=s)`` gives env k seed
s + k; an env reset without a seed (gymnasium's autoreset) takes its last seed + ``num_envs``, its first ``k``, so
the envs never share a condition.

Observation: ``pixels`` {camera: uint8 [H, W, 3]} for each of ``views``, rendered as the collection renders them
(``env.So101Env``), and ``agent_pos`` float32 [14], the simulator's (the collected data's ``observation.state``);
lerobot-eval renames them ``observation.images.<camera>`` and ``observation.state``. Action [4] in ``ACTION_LOW`` ..
``ACTION_HIGH``, clipped there. An episode is ``terminated`` when the simulator ends it (success, or the block out of
the workspace) and ``truncated`` after ``max_steps`` (``EPISODE_STEPS``: the sweep's horizon); ``info["is_success"]``
is the simulator's ``succeed`` so far, so at an end ``info["final_info"]["is_success"]`` is what the sweep's real
episode records (``real.csv``). ``render()``: the views side by side."""
from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np

from sc3_jax.core.errors import UserError
from .collect import FPS, TASK
from .env import ACTION_HIGH, ACTION_LOW, VIEWS, So101Env
from .rollouts import HOLD
from .sweep import EVAL_SEED0, HOLD_STEPS

IMAGE_SIZE = (80, 80)  # `sc3 so101 collect`'s default: a policy sees the size its data was collected at
EPISODE_STEPS = 100  # 10 s at 10 Hz: configs/so101_latent.py's rollout horizon, the sweep's real episodes' length


class So101GymEnv(gym.Env):
    """One SO-101 table (see the module docstring). ``index``, ``stride``: the seeds an unseeded reset takes."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(self, views=VIEWS, image_size=IMAGE_SIZE, max_steps: int = EPISODE_STEPS, index: int = 0,
                 stride: int = 1):
        if max_steps < 1:
            raise UserError(f"max_steps={max_steps}: at least 1")
        self.sim = So101Env(tuple(image_size), views=tuple(views))
        h, w = self.sim.image_size
        image = gym.spaces.Box(0, 255, (h, w, 3), np.uint8)
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({v: image for v in self.sim.views}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (self.sim.state_dim,), np.float32)})
        self.action_space = gym.spaces.Box(ACTION_LOW, ACTION_HIGH, dtype=np.float32)
        self.render_mode = "rgb_array"
        self._max_episode_steps = int(max_steps)  # what lerobot-eval reads (env.call("_max_episode_steps"))
        self.task = self.task_description = TASK
        self.index, self.stride = int(index), int(stride)
        self.condition: int | None = None

    def reset(self, *, seed=None, options=None):
        if seed is not None and int(seed) < 0:
            raise UserError(f"reset(seed={seed}): a condition of the sweep, 0 or more")
        super().reset(seed=seed)
        if seed is None:
            seed = self.index if self.condition is None else self.condition + self.stride
        obs = self.sim.reset(EVAL_SEED0 + int(seed))
        for _ in range(HOLD_STEPS):
            obs, _, _ = self.sim.step(HOLD)
        self.condition, self.t, self.success = int(seed), 0, False
        return self._observation(obs), {"seed": self.condition}

    def step(self, action):
        obs, ok, done = self.sim.step(action)
        self.t += 1
        self.success = self.success or ok
        truncated = not done and self.t >= self._max_episode_steps
        return self._observation(obs), float(ok), done, truncated, {"is_success": self.success,
                                                                    "seed": self.condition}

    def render(self) -> np.ndarray:
        """uint8 [H, V * W, 3]: the views now, side by side."""
        return np.concatenate(list(self.sim.render_views()), axis=1)

    def close(self) -> None:
        self.sim.close()

    def _observation(self, obs: dict) -> dict:
        return {"pixels": dict(zip(self.sim.views, self.sim.render_views())),
                "agent_pos": np.asarray(obs["agent_pos"], np.float32)}


def vec_env(num_envs: int = 1, views=VIEWS, image_size=IMAGE_SIZE, max_steps: int = EPISODE_STEPS,
            asynchronous: bool = False) -> gym.vector.VectorEnv:
    """``num_envs`` tables, stepped in this process (``asynchronous``: one worker process each), SAME_STEP
    autoreset (a finished env's ``final_info`` and its next episode's first observation in the same step)."""
    if num_envs < 1:
        raise UserError(f"num_envs={num_envs}: at least 1")
    make = [functools.partial(So101GymEnv, tuple(views), tuple(image_size), max_steps, k, num_envs)
            for k in range(num_envs)]
    mode = gym.vector.AutoresetMode.SAME_STEP
    if asynchronous and num_envs > 1:
        return gym.vector.AsyncVectorEnv(make, autoreset_mode=mode, context="spawn")
    return gym.vector.SyncVectorEnv(make, autoreset_mode=mode)
