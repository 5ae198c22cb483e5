"""``--env.type=sc3``: LeRobot's env config for an sc3_jax world model (README.md). Imported by lerobot-eval's
``register_third_party_plugins`` because this distribution is named ``lerobot_env_sc3``.

The features LeRobot builds a policy's inputs from (``env_to_policy_features``) are read from the saved world model
(``sc3_jax.model.checkpoint.read_robot``: cameras, image size, action and state sizes, frame rate), so the config names
no robot. The env is ``sc3_jax.evaluation.gym_env.WorldModelVecEnv`` with the raw-env keys (``pixels/<camera>``,
``agent_pos``) that lerobot-eval's ``preprocess_observation`` renames to ``observation.images.<camera>`` and
``observation.state``; its ``num_envs`` episodes are batched in one world-model call, so ``use_async_envs`` (worker
processes, one env each) does not apply and is ignored."""
from __future__ import annotations

import math
from dataclasses import dataclass

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

NAME = "sc3"


@EnvConfig.register_subclass(NAME)
@dataclass
class SC3WorldModelEnv(EnvConfig):
    task: str | None = "world_model"
    world_model: str = ""
    """a training run (checkpoints/) or an exported world model (params.npz)"""
    initial_conditions: str = ""
    """held-out episodes (an episode store) or an .npz of initial conditions"""
    scorer: str = ""
    """package.module:attr (a RolloutView -> {criterion: bool}) or detector:DIR"""
    criterion: str = "success"
    action_steps: int | None = None
    """actions per world-model call (the policy's n_action_steps); None: the model's rollout.keep_frames"""
    tau: float = math.inf
    episode_seconds: float | None = None
    sample_steps: int | None = 2
    inverse_steps: int | None = 1
    rollout_seed: int = 0
    learned_state: bool = True
    start: int = 0

    def __post_init__(self):
        if not self.world_model:  # `lerobot-eval --help`, or a config built before its fields are set
            return
        from sc3_jax.model import checkpoint
        from sc3_jax.core.errors import UserError

        try:
            cfg = checkpoint.read_config(self.world_model)
            robot = checkpoint.read_robot(self.world_model, cfg)
        except UserError as e:
            raise ValueError(f"--env.world_model={self.world_model}: {e}") from None
        h, w = cfg.data.image_size
        r = cfg.rollout
        self.fps = int(round(r.policy_hz or r.control_hz))
        state = robot.state_dim if (self.learned_state and _has_head(self.world_model)) else robot.action_space.dim
        self.features = {ACTION: PolicyFeature(FeatureType.ACTION, (robot.action_space.dim,)),
                         "agent_pos": PolicyFeature(FeatureType.STATE, (state,)),
                         **{f"pixels/{v}": PolicyFeature(FeatureType.VISUAL, (h, w, 3)) for v in robot.views}}
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE,
                             **{f"pixels/{v}": f"{OBS_IMAGES}.{v}" for v in robot.views}}

    @property
    def gym_kwargs(self) -> dict:
        return dict(scorer=self.scorer, criterion=self.criterion, action_steps=self.action_steps, tau=self.tau,
                    keys="gym", start=self.start, learned_state=self.learned_state, rollout_seed=self.rollout_seed,
                    sample_steps=self.sample_steps, inverse_steps=self.inverse_steps,
                    episode_seconds=self.episode_seconds)

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        from sc3_jax.evaluation.gym_env import WorldModelVecEnv

        missing = [f"--env.{k}" for k in ("world_model", "initial_conditions", "scorer") if not getattr(self, k)]
        if missing:
            raise ValueError(f"--env.type={NAME} needs {', '.join(missing)} (see lerobot_env_sc3's README)")
        env = WorldModelVecEnv(self.world_model, self.initial_conditions, n_envs, **self.gym_kwargs)
        return {NAME: {0: env}}


def _has_head(world_model: str) -> bool:
    """Whether the world model has a learned robot state (what the env hands the policy then)."""
    from pathlib import Path

    from sc3_jax.rollout import state_head

    return (Path(world_model) / state_head.FILE).is_file()


from . import so101  # noqa: E402, F401  (registers --env.type=sc3_so101: the SO-101 simulator on our cameras)
