"""``--env.type=sc3_so101``: the SO-101 simulator on our benchmark's cameras and initial conditions, for a LeRobot
policy trained on ``sc3 so101 collect``'s data (the simulator's own ``--env.type=so101`` renders only its ``front``
room camera). The env is ``sc3_jax.benchmarks.so101.vec_env`` (its docstring: seeds, observation, ends); this only
maps LeRobot's config onto it. The defaults (cameras, image size, horizon) are that module's, read when a config is
built, not when lerobot imports this plugin: set ``--env.views`` / ``--env.image_size`` to what the policy's data was
collected with."""
from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

NAME = "sc3_so101"


def _default(name: str):
    def read():
        from sc3_jax.benchmarks.so101 import vec_env
        return list(getattr(vec_env, name))
    return field(default_factory=read)


@EnvConfig.register_subclass(NAME)
@dataclass
class SC3So101Env(EnvConfig):
    task: str | None = "so101_pick_place"
    fps: int = 10
    views: list[str] = _default("VIEWS")
    """the cameras, in the order of the policy's observation.images.<camera> (workspace, wrist, front)"""
    image_size: list[int] = _default("IMAGE_SIZE")
    """H W of every camera"""
    episode_length: int | None = None
    """steps before an episode is truncated (None: the sweep's horizon, vec_env.EPISODE_STEPS)"""

    def __post_init__(self):
        from sc3_jax.benchmarks.so101.env import So101Env, check_views
        from sc3_jax.core.errors import UserError

        try:  # a wrong camera or size is one line naming the option, before a policy loads or a table starts
            check_views(self.views)
            if len(self.image_size) != 2 or min(self.image_size) < 1:
                raise UserError(f"{list(self.image_size)}: H W, both positive")
        except UserError as e:
            raise ValueError(f"--env.views={self.views} --env.image_size={self.image_size}: {e}") from None
        h, w = self.image_size
        self.features = {ACTION: PolicyFeature(FeatureType.ACTION, (So101Env.action_dim,)),
                         "agent_pos": PolicyFeature(FeatureType.STATE, (So101Env.state_dim,)),
                         **{f"pixels/{v}": PolicyFeature(FeatureType.VISUAL, (h, w, 3)) for v in self.views}}
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE,
                             **{f"pixels/{v}": f"{OBS_IMAGES}.{v}" for v in self.views}}

    @property
    def gym_kwargs(self) -> dict:
        from sc3_jax.benchmarks.so101 import vec_env

        return dict(views=tuple(self.views), image_size=tuple(self.image_size),
                    max_steps=self.episode_length or vec_env.EPISODE_STEPS)

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        from sc3_jax.benchmarks.so101 import vec_env

        return {NAME: {0: vec_env.vec_env(n_envs, asynchronous=use_async_envs, **self.gym_kwargs)}}
