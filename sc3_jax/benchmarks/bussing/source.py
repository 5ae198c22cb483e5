"""What the bussing benchmark hands the sweep engine (``evaluation/engine.py``'s ``Source``): its initial conditions
(the simulator's reset frames and end-effector pose per seed and task), its real rollouts (the simulator, scored
by physics and by the perception scorer) and its outcome scorer on imagined frames (one outcome per object, for the
rollout cut after every chunk). Built once per process that rolls out; the simulator and the perception network
load when first used."""
from __future__ import annotations

import numpy as np

from sc3_jax.evaluation.results import rollout_id


def initial_observation(env, seed: int, task: str):
    """Frames uint8 [V, H, W, 3] and end-effector pose [7] right after reset: where real and imagined start."""
    env.reset(seed, task)
    f = env.render()
    return np.stack([f[v] for v in env.views]), env.ee_pose().astype(np.float32)


class BussingSource:
    """``tasks``: policy name -> its task; ``image_size`` the frames' (the world model's); ``weights`` the perception
    scorer's; ``max_steps`` a real rollout's horizon; ``score_stride`` the frame stride real rollouts are scored at
    (the world model's, so real and imagined rollouts are read alike)."""

    outcomes = "objects"  # one outcome per object
    every_cut = True  # one perception pass serves every cut, so a report may try any tau
    keeps = ("reread",)  # the actions the inverse mode re-read

    def __init__(self, tasks: dict[str, str], image_size: tuple[int, int], weights: str, max_steps: int,
                 score_stride: int, env=None, scorer=None):
        self.tasks, self.image_size, self.weights = dict(tasks), tuple(image_size), weights
        self.max_steps, self.score_stride = max_steps, score_stride
        self._env, self._scorer = env, scorer

    @property
    def env(self):
        if self._env is None:
            from .policy_eval import make_env
            self._env = make_env(self.image_size)
        return self._env

    @property
    def scorer(self):
        if self._scorer is None:
            from . import perception
            from .scorers import PerceptionScorer
            self._scorer = PerceptionScorer(perception.load(self.weights))
        return self._scorer

    def fields(self, job, seed: int) -> dict:
        from .tasks import SPLITS
        task = self.tasks[job.name]
        return {"task": task, "split": SPLITS[task]}

    def conditions(self, job, spec):
        """The reset frames, repeated over the world model's ``spec.context`` frames (the scene at rest), and the
        end-effector pose."""
        from sc3_jax.rollout import rollout

        from .tasks import task_id
        task = self.tasks[job.name]
        obs = [initial_observation(self.env, seed, task) for seed in job.seeds]
        frames = np.stack([np.repeat(f[:, None], spec.context, 1) for f, _ in obs])  # [B, V, K, H, W, 3]
        return rollout.InitialConditions(frames, np.stack([p for _, p in obs]), np.full(len(obs), task_id(task)))

    def score(self, job, b: int, frames: np.ndarray, states, cuts, keep: int) -> dict:
        from .tasks import make_initial_condition
        ic = make_initial_condition(job.seeds[b], self.tasks[job.name])
        n = max(cuts)
        every = self.scorer.score_cuts(frames, ic.objects, ic.destinations(), keep, n, prefix=1)
        return {c: every[c] for c in cuts}

    def real(self, job, policy) -> tuple[dict, dict]:
        """One simulated rollout, scored by physics and by perception (on every ``score_stride``-th frame and the
        last); with ``job.degraded`` also by perception on degraded copies of the frames (``degrade.py``: how the
        scorer reads generated-looking frames)."""
        from sc3_jax.evaluation.scorers import RolloutView

        from .policy_eval import run_policy_episode
        from .scorers import SimScorer
        env, seed, task = self.env, job.seeds[0], self.tasks[job.name]
        r = run_policy_episode(env, policy, seed, task, record=True, max_steps=self.max_steps)
        frames = np.stack([r.frames[v] for v in env.views])  # [V, T, H, W, 3] at 20 Hz
        view = RolloutView(rollout_id(job.name, seed, "real"), frames, r.ic.objects, r.ic.destinations(),
                           [o.to_json() for o in r.outcomes])
        clean, degraded = self.scorer.score_real(view, seed, self.score_stride, job.degraded)
        rec = {"objects": SimScorer().score(view), "perception": clean, "length": int(r.length),
               "prompt": r.ic.prompt, "score_stride": self.score_stride}
        if job.degraded:
            rec["perception_degraded"] = degraded
        return rec, {"frames": frames, "actions": r.actions.astype(np.float32),
                     "ee_pose": r.ee_pose.astype(np.float32), "object_pos": r.object_pos}

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


def state_reader(weights: str):
    """The gripper-state reader of the perception weights ``weights`` (``rollout.Rollout``'s ``state_reader``)."""
    from . import perception
    return perception.state_reader(perception.load(weights))
