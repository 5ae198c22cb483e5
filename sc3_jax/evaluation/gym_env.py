"""The world model as a gymnasium vector environment: any gymnasium loop (``lerobot-eval`` through
``plugins/lerobot_env_sc3``, a lab's own script) runs its policy inside the imagined world, unchanged.

    env = WorldModelVecEnv("RUN", "HELDOUT", num_envs=4, scorer="pkg.mod:score")
    obs, info = env.reset(seed=0)                      # conditions 0..3 of HELDOUT
    obs, reward, terminated, truncated, info = env.step(actions)   # actions [4, A] raw, one per env

It is the same closed loop as ``sc3 sweep episodes`` (``evaluation/ic_sweep.py``): ``rollout.Rollout``'s jitted
``observe`` and model step, the N envs batched in one world-model call, and the same per-condition noise, so the
same conditions, seeds and policy give the same imagined outcomes (tests/test_gym_env.py holds it to that).

Chunk-synchronous. The world model imagines l kept frames per call (``rollout.keep_frames``; it predicts l' >= l and
discards the rest). The env therefore *collects* ``action_steps`` = l x policy_hz / control_hz actions, one per
``step``, and only on the last of them runs the model and returns the observation of the last kept frame. The
steps in between return the observation the chunk started from again (and reward 0). A policy that executes
``action_steps`` actions per inference (LeRobot's ``n_action_steps``) sees exactly what it would see in the sweep.
A policy that replans more often sees that same, stale observation on its extra replans: it cannot react inside a
chunk, so set ``action_steps`` to its ``n_action_steps`` (it must be a multiple of policy_hz / control_hz and at most
l' of them; the model's own l by default). The actions after the last collected one, which condition the discarded
frames, hold the last action (``rollout.fill_chunk``).

Seeds and conditions: ``reset(seed=s)`` puts condition ``s mod n`` (n: the conditions given) in env 0, ``s + 1`` in
env 1, ...; a list gives each env its seed; None takes the next unused seeds. Env seed ``s`` draws the world model's
noise from ``(rollout_seed, s)``: seed i < n is exactly the sweep's condition i (``--rollout-seed`` the same).

Observations, in LeRobot's keys (``keys="lerobot"``): ``observation.images.<view>`` uint8 [H, W, 3] per camera (the
world model's views, read from the saved model) and ``observation.state`` float32: the learned robot state where the
model has one (``state_head.npz``), else the imagined commanded state. ``keys="gym"`` gives the raw-env spelling
that ``lerobot-eval`` renames into those (``pixels: {view: image}``, ``agent_pos``).

Ends: ``truncated`` at the horizon (``rollout.episode_seconds``), ``terminated`` when the chunk's U exceeds ``tau``
(the world model no longer follows the actions; that chunk's frames are not kept). At an end the scorer reads the
kept frames and states (a ``RolloutView``, as the sweep's) and ``info["final_info"]["is_success"]`` is its
``criterion`` (reward 1.0 then, else 0); the env then resets to the next seed in the same step (gymnasium's
``SAME_STEP`` autoreset, what ``lerobot-eval`` reads). Videos (``render``): the current observation's views side by
side, so a frame is held for a chunk."""
from __future__ import annotations

import fractions
import math
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError

KEYS = ("lerobot", "gym")


def _mesh(batch: int):
    """As many local devices as divide the batch (the sweep's rule: the same mesh, the same programs)."""
    import jax

    from sc3_jax.model import sharding
    from sc3_jax.core.config import MeshConfig

    devices = jax.local_devices()
    d = max(k for k in range(1, min(batch, len(devices)) + 1) if batch % k == 0)
    return sharding.make_mesh(MeshConfig(-1, 1, 1), devices[:d])


def _conditions(source, wcfg, spec, start: int, task: int):
    """(ids, InitialConditions, prompts): an episode store or .npz path (``rollout_io.load_initial_conditions``),
    or (ids, InitialConditions) already built (a benchmark's own conditions)."""
    from sc3_jax.core import atomic
    from sc3_jax.rollout import rollout_io

    if not isinstance(source, (str, Path)):
        ids, ics = source
        return list(ids), ics, [""] * len(ids)
    ids, ics, store = rollout_io.load_initial_conditions(str(source), wcfg, spec, None, start, task)
    prompts = [atomic.read_json(store.root / e / "meta.json").get("prompt", "") if store else "" for e in ids]
    return ids, ics, prompts


def _vector_env_base():
    try:
        import gymnasium
    except ImportError:
        raise UserError("the world model as a gymnasium env needs gymnasium: pip install 'sc3_jax[gym]'") from None
    return gymnasium


gym = _vector_env_base()


class WorldModelVecEnv(gym.vector.VectorEnv):
    """``num_envs`` imagined episodes of the world model at ``world_model`` (a training run or an exported dir) from
    the initial conditions ``initial_conditions`` (an episode store of held-out episodes or an .npz, as ``sc3 sweep
    episodes --data`` reads them), scored by ``scorer`` (``package.module:attr`` or ``detector:DIR``, the sweep's
    ``--scorer``; or a callable taking a ``RolloutView``). Sampler settings are the sweep's (``Sampler``'s defaults).
    See the module docstring for the chunking, seeding and observation contract."""

    def __init__(self, world_model: str, initial_conditions, num_envs: int = 1, *, scorer,
                 criterion: str = "success", action_steps: int | None = None, tau: float | None = math.inf,
                 keys: str = "lerobot", start: int = 0, task: int = 0, learned_state: bool = True,
                 rollout_seed: int = 0, sample_steps: int | None = 2, inverse_steps: int | None = 1,
                 episode_seconds: float | None = None, tau_units: str = "raw"):
        import jax

        from sc3_jax.model import checkpoint
        from sc3_jax.core import config
        from sc3_jax.rollout import rollout, state_head
        from sc3_jax.evaluation.scorers import load_outcome_scorer
        from sc3_jax.evaluation.world_model_defaults import Sampler, evaluation_config

        if keys not in KEYS:
            raise UserError(f"keys={keys!r}: one of {', '.join(KEYS)}")
        if num_envs < 1:
            raise UserError(f"num_envs={num_envs}: at least 1")
        self.scorer_spec = scorer if isinstance(scorer, str) else getattr(scorer, "__name__", type(scorer).__name__)
        self._score = load_outcome_scorer(scorer) if isinstance(scorer, str) else scorer
        self.criterion, self.keys, self.rollout_seed = criterion, keys, int(rollout_seed)
        wcfg, stats, params = checkpoint.load(world_model)
        wcfg = evaluation_config(wcfg, Sampler(sample_steps=sample_steps, inverse_steps=inverse_steps,
                                               episode_seconds=episode_seconds, tau_units=tau_units))
        robot = checkpoint.read_robot(world_model, wcfg)
        if action_steps is not None:  # l matched to the policy's n_action_steps
            wcfg = config.replace(wcfg, rollout=self._keep_for(wcfg, action_steps))
        self.ro = rollout.Rollout(wcfg, stats, mesh=_mesh(num_envs), data_fps=robot.fps,
                                  head=state_head.load(world_model) if learned_state else None)
        s = self.spec = self.ro.spec
        self.tau = self.ro.tau if tau is None else float(tau)
        self.views = tuple(wcfg.data.views)
        self.ids, self.ics, self.prompts = _conditions(initial_conditions, wcfg, s, start, task)
        self.params = self.ro.place_params(params)
        self.action_steps = s.executed
        self.max_episode_steps = s.num_chunks * s.executed
        self.num_envs = int(num_envs)
        self.learned = bool(s.state_dim)
        seen = s.state_dim or s.action_dim
        H, W = s.image_size
        image = gym.spaces.Box(0, 255, (H, W, 3), np.uint8)
        state = gym.spaces.Box(-np.inf, np.inf, (seen,), np.float32)
        if keys == "lerobot":
            single = {f"observation.images.{v}": image for v in self.views} | {"observation.state": state}
        else:
            single = {"pixels": gym.spaces.Dict({v: image for v in self.views}), "agent_pos": state}
        self.single_observation_space = gym.spaces.Dict(single)
        self.single_action_space = gym.spaces.Box(-np.inf, np.inf, (s.action_dim,), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        fps = s.ratio / s.model_dt  # policy actions per second; an int where it is one: video writers want an int
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": int(round(fps)) if abs(fps - round(fps)) < 1e-9
                         else fractions.Fraction(fps).limit_denominator(1000),
                         "autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}
        self.render_mode = "rgb_array"
        self._jax = jax
        self._carry = None
        self._next_seed = 0

    @staticmethod
    def _keep_for(wcfg, action_steps: int) -> dict:
        """rollout fields for ``action_steps`` policy actions per world-model call."""
        r = wcfg.rollout
        ratio = int(round((r.policy_hz or r.control_hz) / r.control_hz))
        keep, rem = divmod(int(action_steps), ratio)
        if rem or not 1 <= keep <= wcfg.data.future_frames:
            raise UserError(f"action_steps={action_steps}: a multiple of {ratio} (policy_hz / control_hz) of at most "
                            f"{wcfg.data.future_frames * ratio} actions (the {wcfg.data.future_frames} frames the "
                            "world model predicts per call)")
        return dict(keep_frames=keep, policy_chunk=max(r.policy_chunk, keep * ratio))

    # -- gymnasium -----------------------------------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        if seed is None:
            seeds = [self._next_seed + i for i in range(self.num_envs)]
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(int(seed))
        else:
            seeds = [int(x) for x in seed]
            if len(seeds) != self.num_envs:
                raise UserError(f"reset(seed=[...]): {len(seeds)} seeds for {self.num_envs} envs")
        self._seeds = np.asarray(seeds, np.int64)
        self._next_seed = int(self._seeds.max()) + 1
        self._carry = None
        self._start(np.ones(self.num_envs, bool))
        self._t = 0
        return self._observation(), {"seed": self._seeds.copy(), "episode": np.asarray(self._episode_ids())}

    def step(self, actions):
        if self._carry is None:
            raise UserError("step() before reset(): call reset(seed=...) first")
        a = np.asarray(actions, np.float32)
        want = (self.num_envs, self.spec.action_dim)
        if a.shape != want:
            raise UserError(f"actions {list(a.shape)}: the world model takes [num_envs={want[0]}, {want[1]}] "
                            f"({self.spec.action_space.kind} actions)")
        self._actions[:, self._t] = a
        self._t += 1
        N = self.num_envs
        zeros = np.zeros(N, bool)
        if self._t < self.action_steps:  # mid-chunk: nothing imagined yet
            return self._obs, np.zeros(N), zeros, zeros.copy(), {}
        self._t = 0
        done, u, u_raw = self._imagine()
        self._chunks += 1
        truncated = ~done & (self._chunks >= self.spec.num_chunks)
        terminated = done
        ended = terminated | truncated
        obs = self._observation()
        info = {"u": u, "_u": np.ones(N, bool), "u_raw": u_raw, "_u_raw": np.ones(N, bool)}
        reward = np.zeros(N)
        if ended.any():
            success = np.zeros(N, bool)
            outcomes = np.empty(N, object)
            for i in np.flatnonzero(ended):
                outcomes[i] = self._outcome(i)
                success[i] = outcomes[i][self.criterion]
            reward[success] = 1.0
            info["final_info"] = {"is_success": success, "_is_success": ended.copy(),
                                  "outcomes": outcomes, "_outcomes": ended.copy(),
                                  "episode": np.asarray(self._episode_ids(), object), "_episode": ended.copy(),
                                  "seed": self._seeds.copy(), "_seed": ended.copy()}
            info["final_obs"] = np.array([{k: v[i] for k, v in _flat(obs).items()} for i in range(N)], object)
            info["_final_obs"], info["_final_info"] = ended.copy(), ended.copy()
            info["is_success"], info["_is_success"] = success.copy(), ended.copy()
            nxt = self._next_seed + np.cumsum(ended) - 1  # the next unused seeds, in env order
            self._seeds = np.where(ended, nxt, self._seeds)
            self._next_seed += int(ended.sum())
            self._start(ended)
            obs = self._observation()
        return obs, reward, terminated, truncated, info

    def render(self):
        """uint8 [H, V * W, 3] of env 0 (``call("render")`` gives every env's)."""
        return self._frame(0)

    def call(self, name: str, *args, **kwargs) -> tuple:
        """Per-env values, as a SyncVectorEnv's ``call``: ``render``, ``task_description`` / ``task`` (the
        condition's prompt), ``_max_episode_steps``; any other attribute of this env, once per env."""
        N = range(self.num_envs)
        if name == "render":
            return tuple(self._frame(i) for i in N)
        if name in ("task_description", "task"):
            return tuple(self.prompts[int(s) % len(self.ids)] for s in self._seeds)
        if name == "_max_episode_steps":
            return (self.max_episode_steps,) * self.num_envs
        value = getattr(self, name)
        return tuple(value(*args, **kwargs) if callable(value) else value for _ in N)

    def get_attr(self, name: str) -> tuple:
        return self.call(name)

    def close_extras(self, **kwargs):
        self._carry = None

    # -- the closed loop, per env ----------------------------------------------------------------------------------
    def _episode_ids(self) -> list[str]:
        return [self.ids[int(s) % len(self.ids)] for s in self._seeds]

    def _start(self, which: np.ndarray) -> None:
        """Envs ``which`` begin their episodes at their seeds' conditions (the others keep theirs)."""
        from sc3_jax.rollout import rollout

        jax = self._jax
        idx = self._seeds % len(self.ids)
        ics = self.ics.take(idx)
        keys = np.stack([np.asarray(rollout.episode_keys(self.rollout_seed, 1, start=int(s)))[0]
                         for s in self._seeds])
        B, frames, state, task, dev_keys = self.ro._inputs(ics, keys)
        fresh = jax.device_get(self.ro._init(frames, *state))
        if self._carry is None:
            carry = fresh
            self._chunks = np.zeros(self.num_envs, np.int64)
            self._actions = np.zeros((self.num_envs, self.action_steps, self.spec.action_dim), np.float32)
            self._hist = [None] * self.num_envs
        else:
            pad = np.zeros(len(fresh.done), bool)
            pad[:B] = which
            old = jax.device_get(self._carry)
            carry = jax.tree.map(lambda n, o: np.where(pad.reshape((-1,) + (1,) * (n.ndim - 1)), n, o), fresh, old)
            self._chunks[which] = 0
        self._carry = jax.tree.map(lambda x: self.ro._pad(x, len(x)), carry)
        self._task, self._keys = task, dev_keys
        first = ics.robot if self.learned else ics.state
        for i in np.flatnonzero(which):
            self._hist[i] = ([np.asarray(ics.frames[i][:, -1:])], [np.asarray(first[i], np.float32)[None]])

    def _imagine(self):
        """One world-model call for every env: the collected actions -> the next carry; returns (done, u, u_raw)."""
        from sc3_jax.rollout.rollout import fill_chunk

        jax, s = self._jax, self.spec
        acts = fill_chunk(self._actions, s.step_actions)
        self._carry, emit = self.ro._model_step(self.params, self._carry, self.ro._pad(acts, len(self._keys)),
                                                self._keys, np.float32(self.tau))
        emit = jax.device_get(emit)
        N = self.num_envs
        done = np.asarray(emit["done"], bool)[:N]
        states = emit["robot_states" if self.learned else "states"]
        for i in np.flatnonzero(~done):  # a chunk over tau is not kept (rollout.py), nor scored
            self._hist[i][0].append(np.asarray(emit["frames"][i]))
            self._hist[i][1].append(np.asarray(states[i], np.float32))
        return done, np.asarray(emit["u"], np.float32)[:N], np.asarray(emit["u_raw"], np.float32)[:N]

    def _outcome(self, i: int) -> dict:
        from sc3_jax.evaluation.scorers import RolloutView, check_outcomes

        frames, states = self._hist[i]
        c = int(self._seeds[i]) % len(self.ids)
        view = RolloutView(self.ids[c], np.concatenate(frames, 1), state=np.concatenate(states, 0),
                           instruction=self.prompts[c])
        got = check_outcomes(self.scorer_spec, self._score(view), f"env {i} (seed {self._seeds[i]})")
        if self.criterion not in got:
            raise UserError(f"scorer {self.scorer_spec}: criteria {sorted(got)}, the env reads criterion="
                            f"{self.criterion!r}; pass one of those")
        return got

    def _observation(self) -> dict:
        obs, _ = self._jax.device_get(self.ro._observe(self._carry, self._task, self._keys, self.ro.reader_params))
        N = self.num_envs
        images = np.asarray(obs["images"])[:N]  # [N, V, H, W, 3]
        state = np.asarray(obs["state"], np.float32)[:N]
        self._images = images
        if self.keys == "lerobot":
            out = {f"observation.images.{v}": images[:, j] for j, v in enumerate(self.views)}
            out["observation.state"] = state
        else:
            out = {"pixels": {v: images[:, j] for j, v in enumerate(self.views)}, "agent_pos": state}
        self._obs = out
        return out

    def _frame(self, i: int) -> np.ndarray:
        return np.concatenate(list(self._images[i]), axis=1)


def _flat(obs: dict) -> dict:
    """{key: [N, ...]} of a (possibly nested, keys="gym") batched observation, nested keys joined by '/'."""
    out = {}
    for k, v in obs.items():
        if isinstance(v, dict):
            out.update({f"{k}/{kk}": vv for kk, vv in v.items()})
        else:
            out[k] = v
    return out
