"""Closed-loop rollouts inside the world model (the paper's Algorithm 1), on device, and offline (open-loop) replay.

One chunk (per initial condition; ``vmap`` over a batch of them, the batch sharded over the mesh's data axes):

    obs      = (last context frame of every view as uint8, imagined state, task)
    a[0:C]   = policy(obs, k_policy)                      raw actions, C = policy chunk (25) >= l' (24)
    v[0:l']  = FD-sample(context, normalise(a[0:l']))     S Euler steps (flow.sample), every view
    â[0:l']  = ID-sample(context, v[0:l'])                re-read the actions from the predicted frames (its own
                                                          step count, sample.inverse_steps; default S)
    U        = mean_{i<l} ||a_i - denormalise(â_i)||_2    l = kept frames (16), in rollout.tau_units (raw by default)
    done'    = done | (U > tau)
    if not done': context = last K frames of [context, v[0:l]];  state = integrate(state, a[0:l])
    emit (decode(v[0:l]) as uint8, a[0:l], denormalise(â[0:l]), U, done')

Decisions (see docs/rollout.md for more):
* Static shapes: the context is a fixed [V, K, H, W, 3] frame buffer, tokenised at every chunk (a causal VAE then
  re-encodes the sliding window from its first frame, as in training), updated by a static concat + slice (the ring
  buffer, kept in temporal order because the model's RoPE positions are frame indices); termination is a mask.
  A chunk whose U exceeds tau is *not* pushed into the context and everything after it is marked invalid; the scan
  still computes the later chunks (on the frozen context) so shapes stay static. Their U values are emitted but are
  not those of an untruncated rollout: to sweep tau after the fact run once with ``tau=inf`` and cut with
  ``evaluation.results.terminated_at`` -- identical, up to the termination chunk, to a run with that tau.
* U is the mean over the l kept steps of the L2 norm over the A action dimensions, in ``cfg.rollout.tau_units``:
  "raw" (the paper's units, in which its tau = 0.02 is set; the default) or "normalised" (per-dimension unit
  variance). Both are emitted (``u_raw``, ``u``); the one in tau_units decides termination. tau comes from the
  caller or the saved config (``rollout.tau``; None: :func:`resolve_tau`, no early termination): its value is in an
  action space's raw units, a benchmark's to set (the bussing benchmark's paper value: benchmarks/bussing/hooks.py).
* Robot facts (the data's frame rate, the action space, the views) come from the saved model
  (``checkpoint.read_robot``), never from a default here: ``Rollout`` / :func:`make_spec` require them.
* Frames advance at ``control_hz``: the model runs with frame stride ``round(data_fps / control_hz)`` (20 Hz data,
  10 Hz control -> 2) and one policy action per predicted frame.
* Actions and state: in the action space the world model was trained in (``NormStats.action_space``, from its
  ``norm_stats.json``; ``data/action_space.py``): delta_ee for the simulated benchmark, absolute targets or
  velocities of any dimension A. No simulator, so the commanded actions are integrated onto the initial state
  (``sc3_jax.rollout.imagination_state``; delta_ee: the end-effector pose, absolute: the last target, velocity: at 1 /
  policy_hz seconds per action); only the l executed actions of each chunk are integrated. A policy's declared
  ``action_dim`` (and its first chunk's shape, by ``jax.eval_shape``) is checked before anything compiles.
* Randomness: episode ``b`` has its own key; chunk ``c`` uses ``fold_in(key_b, c)`` split into (policy, FD, ID)
  keys. Results therefore do not depend on the batch composition or the number of devices, and the host loop
  (:meth:`Rollout.run_host`) reproduces the scan (:meth:`Rollout.run`) by driving the very same per-chunk functions
  (observe -> policy on the host -> model step).
* Context caching: with ``cfg.model.context_attention == "causal"`` the forward sampler reuses the context's
  keys/values over its S Euler steps and the inverse sampler those of every frame (each step then runs only the
  action tokens); the context's are computed once for both (``flow.shares_context``: unless each noises it with its
  own key). ``Rollout(..., cache=False)`` forces the uncached path, for checks and benchmarks.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.model import flow, modes, sharding
from sc3_jax.rollout import imagination_state, state_head
from sc3_jax.core.config import Config, MeshConfig
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.core.errors import UserError
from sc3_jax.model import dit
from sc3_jax.model.tokenizer import make_tokenizer, to_uint8, to_unit, window_tokens
from sc3_jax.policies.base import JaxPolicy, as_host, check_dims


# ================================================================================================================
# Static description of a rollout
# ================================================================================================================
@dataclasses.dataclass(frozen=True)
class RolloutSpec:
    views: int
    image_size: tuple[int, int]
    context: int  # K
    predict: int  # l'
    keep: int  # l
    policy_chunk: int  # C
    num_chunks: int
    stride: int
    steps: int  # Euler steps per forward-dynamics sampler call (sample.steps)
    action_space: ActionSpace  # what the actions mean (compose, imagined state, holding still): the model's
    data_fps: float  # the frame rate of the data the model was trained on (checkpoint.read_robot)
    ratio: int = 1  # raw policy actions per model-rate action (policy_hz / control_hz)
    context_noise: float = 0.0  # noise level on the context at inference (models trained with context noise)
    tau_units: str = "raw"  # the units U_chunk is compared with tau in (RolloutConfig.tau_units)
    inverse_steps: int | None = None  # Euler steps of the inverse-dynamics re-read (None: steps)
    state_dim: int = 0  # the learned robot state's size (state_head.py); 0: policies see the imagined commands
    anchor: int = 0  # 1: the first observation kept in front of every chunk's context (data.anchor)

    @property
    def action_dim(self) -> int:
        return self.action_space.dim

    @property
    def model_dt(self) -> float:
        """Seconds per model-rate action (one predicted frame)."""
        return self.stride / self.data_fps

    @property
    def raw_dt(self) -> float:
        """Seconds per raw policy action."""
        return self.model_dt / self.ratio

    @property
    def raw_needed(self) -> int:
        """Raw policy actions one chunk needs: one model-rate action per predicted frame."""
        return self.predict * self.ratio

    @property
    def executed(self) -> int:
        """Raw policy actions one chunk executes (the kept frames'); the fewest a policy may propose."""
        return self.keep * self.ratio

    @property
    def step_actions(self) -> int:
        """Raw actions one model step takes: the policy's chunk, extended to ``raw_needed`` by holding its last
        action where it plans fewer than the model predicts (those frames are discarded, ``keep`` < ``predict``)."""
        return max(self.policy_chunk, self.raw_needed)

    @property
    def num_frames(self) -> int:
        return self.num_chunks * self.keep


def make_spec(cfg: Config, data_fps: float, num_chunks: int | None = None, *, action_space: ActionSpace,
              state_dim: int = 0) -> RolloutSpec:
    """``data_fps``: the frame rate of the world model's data and ``action_space`` its actions' space (both from the
    saved model: ``checkpoint.read_robot``, or ``NormStats.action_space``). ``state_dim``: its learned state's size
    (0: none)."""
    r, d = cfg.rollout, cfg.data
    space = action_space
    if space.dim != cfg.model.action_dim:
        raise UserError(f"the action space (norm_stats.json) is {space.dim}-D, the model's "
                        f"model.action_dim is {cfg.model.action_dim}")
    if not 1 <= r.keep_frames <= d.future_frames:
        raise UserError(f"rollout.keep_frames={r.keep_frames} must be in [1, data.future_frames={d.future_frames}]")
    ratio = (r.policy_hz or r.control_hz) / r.control_hz
    if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        raise UserError(f"rollout.policy_hz {r.policy_hz} / control_hz {r.control_hz} is not a positive integer")
    ratio = int(round(ratio))
    if r.policy_chunk < r.keep_frames * ratio:  # a chunk may stop short of the discarded frames, not the kept ones
        raise UserError(f"rollout.policy_chunk={r.policy_chunk} < rollout.keep_frames={r.keep_frames} x {ratio}: "
                         "the policy must propose an action for every frame the rollout keeps")
    stride = data_fps / r.control_hz
    if abs(stride - round(stride)) > 1e-6 or round(stride) < 1:
        raise UserError(f"data fps {data_fps} / control_hz {r.control_hz} is not a positive integer frame stride")
    if r.tau_units not in ("raw", "normalised"):
        raise UserError(f"rollout.tau_units {r.tau_units!r}: 'raw' or 'normalised'")
    if num_chunks is None:
        num_chunks = math.ceil(r.episode_seconds * r.control_hz / r.keep_frames - 1e-9)
    return RolloutSpec(len(d.views), tuple(d.image_size), d.context_frames, d.future_frames, r.keep_frames,
                       r.policy_chunk, int(num_chunks), int(round(stride)), cfg.sample.steps, space, float(data_fps),
                       ratio, float(cfg.sample.context_noise), r.tau_units, cfg.sample.inverse_steps,
                       int(state_dim), int(d.anchor))


def resolve_tau(tau: float | None) -> float:
    """``rollout.tau`` as a rollout uses it: as given (by the caller or the saved config), or where None no early
    termination (inf). A tau is in an action space's raw units, so none is assumed here: a benchmark sets its own
    (the bussing benchmark's paper value, ``benchmarks.bussing.hooks.BENCHMARK_TAU``), another robot calibrates one
    on held-out conditions in the dataset's own units (``sc3 sweep episodes --data STORE --taus ...``)."""
    return math.inf if tau is None else float(tau)


class InitialConditions(NamedTuple):
    frames: Any  # uint8 [B, V, K, H, W, 3] the first K context frames (at the rollout's stride)
    state: Any  # float32 [B, A] imagined state at the last context frame (delta_ee: the end-effector pose)
    task: Any  # int32 [B]
    robot: Any = None  # float32 [B, S] the robot's recorded state there (a world model with a learned state)

    def take(self, idx) -> InitialConditions:
        """The conditions at ``idx`` (indices or a slice), each field that is given."""
        return InitialConditions(*(None if x is None else np.asarray(x)[idx] for x in self))


class Carry(NamedTuple):  # one episode (no batch axis); vmapped
    context: jax.Array  # [V, K, H, W, 3] frames in [-1, 1] (tokenised at every chunk)
    state: jax.Array  # [A]
    done: jax.Array  # bool []
    chunk: jax.Array  # int32 []
    robot: jax.Array  # [S] the learned robot state (S = 0: none)
    anchor: jax.Array  # [V, a, H, W, 3] the first observation in [-1, 1] (a = spec.anchor: 1 with data.anchor, else 0)


def fill_chunk(actions, n: int):
    """``actions`` [..., C, A] -> [..., max(C, n), A]: a chunk shorter than the model's window extended by holding
    its last action (the frames those actions condition are predicted and discarded, never kept)."""
    short = n - actions.shape[-2]
    if short <= 0:
        return actions
    xp = np if isinstance(actions, np.ndarray) else jnp  # the host loop pads numpy: no device round trip per episode
    last = actions[..., -1:, :]
    return xp.concatenate([actions, xp.broadcast_to(last, (*last.shape[:-2], short, last.shape[-1]))], axis=-2)


def episode_keys(seed: int, n: int, start: int = 0) -> jax.Array:
    """Per-episode keys (raw uint32 data [n, 2]); episode i's key depends only on (seed, start + i)."""
    base = jax.random.key(seed)
    return jax.vmap(lambda i: jax.random.key_data(jax.random.fold_in(base, i)))(jnp.arange(start, start + n))


# ================================================================================================================
# One chunk (per episode), in the pieces the scan and the host loop share
# ================================================================================================================
class ChunkFns:
    """The per-episode chunk functions, closed over hashable things only (model config, flow config -- it sets the
    sampler's time grid --, spec, cache flag), so their jitted versions are shared by every Rollout with the same
    key (see ``_compiled``). ``cache``: reuse clean keys/values across Euler steps where the model allows it
    (``context_attention="causal"``); False forces the uncached path."""

    def __init__(self, model_cfg, flow_cfg, spec: RolloutSpec, cache: bool = True):
        self.model_cfg, self.flow_cfg, self.spec, self.cache = model_cfg, flow_cfg, spec, cache
        self.tok = make_tokenizer(model_cfg)
        self.grid = self.tok.grid(spec.image_size)
        # token frames of the (context, prediction) window; raises on impossible bookkeeping
        self.window = window_tokens(self.tok, spec.context, spec.predict)

    def init(self, frames, state, robot) -> Carry:
        unit = to_unit(frames)
        return Carry(unit, jnp.asarray(state, jnp.float32), jnp.zeros((), bool), jnp.zeros((), jnp.int32),
                     jnp.asarray(robot, jnp.float32), unit[:, :self.spec.anchor])

    def keys(self, key_data, chunk):
        """(policy, forward, inverse) keys of this chunk."""
        k = jax.random.fold_in(jax.random.wrap_key_data(key_data), chunk)
        return jax.random.split(k, 3)

    def observe(self, carry: Carry, task, key_data, reader_params=None, reader=None):
        """What the policy sees: the last context frame of every view, the state, the task. The state is the learned
        robot state where the world model has one (``spec.state_dim``), else the imagined commanded state; with a
        ``reader`` (a pure ``apply(params, images uint8 [V, H, W, 3]) -> gripper width``) the latter's gripper entry
        is read from the frames: commanded actions cannot tell whether the fingers closed on an object or on air."""
        images = to_uint8(carry.context[:, -1])
        state = carry.robot if self.spec.state_dim else carry.state
        if reader is not None and not self.spec.state_dim:
            state = state.at[6].set(reader(reader_params, images).astype(state.dtype))
        obs = {"images": images, "state": state, "task": jnp.asarray(task, jnp.int32)}
        return obs, jax.random.key_data(self.keys(key_data, carry.chunk)[0])

    def model_step(self, params, norm, carry: Carry, actions, key_data, tau, raw: bool = True):
        """Algorithm 1 after the policy: ``actions`` [C, A] -> (next carry, emitted arrays). ``raw``: the policy's
        actions at ``policy_hz`` (composed ``ratio`` at a time to the model's rate); else already model-rate actions
        (offline replay). ``norm``: (action mean [A], action std [A], state mean, state std) of ``NormStats.arrays``,
        then the learned state's head (``state_head.py``; None without one)."""
        s, m = self.spec, self.model_cfg
        K, T, l, V = s.context, s.predict, s.keep, s.views
        Kt, Tt = self.window  # token frames (= K, T unless the tokenizer compresses time)
        _, k_fd, k_id = self.keys(key_data, carry.chunk)
        mean, std = norm[0], norm[1]
        actions = actions.astype(jnp.float32)
        r = s.ratio if raw else 1
        space = s.action_space
        model_actions = imagination_state.compose(actions[:T * r], r, space)  # [T, A] raw units, model rate
        a = (model_actions - mean) / std  # normalised [T, A]
        stride = jnp.full((1,), s.stride, jnp.int32)
        # data.anchor: the first observation in front of the context, chunk x l x stride data frames before it
        ctx = self.tok.encode(jnp.concatenate([carry.anchor, carry.context], axis=1))[None]  # [1, V, a + Kt, P, D]
        Kt, K = Kt + s.anchor, K + s.anchor
        gap = jnp.full((1,), carry.chunk * l * s.stride, jnp.int32) if s.anchor else None
        video = jnp.concatenate([ctx, jnp.zeros((1, V, Tt) + ctx.shape[3:], ctx.dtype)], axis=2)
        # pose condition: the pose at the last context frame, then integrated with the commanded actions
        pose = (imagination_state.frame_poses(carry.state, model_actions, space, s.model_dt) - norm[2]) / norm[3]
        conditions = dict(grid=self.grid, context_frames=Kt, pose=pose[None] if m.pose_conditioning else None,
                          context_noise=s.context_noise, anchor_gap=gap)
        sample = functools.partial(flow.sample, params, m, steps=s.steps, fcfg=self.flow_cfg, **conditions)
        # forward dynamics: every view's future frames from the context and the commanded actions
        vn, an = modes.fixed(modes.FD, 1, V, Kt, Tt, num_actions=T)
        cached = m.context_attention == "causal" and self.cache
        # the context's keys/values, once for both samplers where both see the same context (its frames as given)
        kv = flow.context_cache(params, m, video, a[None], stride, vn, an, **conditions) \
            if cached and flow.shares_context(m, s.context_noise) else None
        video, _ = sample(video, a[None], stride, vn, an, k_fd, cache="context" if cached else "none", context_kv=kv)
        # inverse dynamics: re-read the actions from the context and the predicted frames
        vn, an = modes.fixed(modes.ID, 1, V, Kt, Tt, num_actions=T)
        _, a_hat = sample(video, jnp.zeros_like(a)[None], stride, vn, an, k_id, cache="video" if cached else "none",
                          steps=s.inverse_steps or s.steps, context_kv=kv)
        a_hat = a_hat[0]
        u = jnp.mean(jnp.linalg.norm(a[:l] - a_hat[:l], axis=-1))  # normalised units
        u_raw = jnp.mean(jnp.linalg.norm(model_actions[:l] - (a_hat[:l] * std + mean), axis=-1))
        done = carry.done | ((u_raw if s.tau_units == "raw" else u) > tau)
        # back to frames, keep the first l: a per-frame tokenizer decodes only those (a third of a chunk's decoder
        # time at l = 8 of 12; bit-identical), a causal VAE decodes the future given the context's latents
        if self.tok.time_compression == 1:
            kept = self.tok.decode(video[0][:, K:K + l], s.image_size)  # [V, l, H, W, 3] in [-1, 1]
        else:
            kept = self.tok.decode(video[0], s.image_size)[:, K:K + l]
        context = jnp.concatenate([carry.context, kept.astype(carry.context.dtype)], axis=1)[:, -s.context:]
        # the l executed steps: l * r raw actions; the state at each kept frame is every r-th integrated state
        state, states = imagination_state.integrate(carry.state, actions[:l * r], space,
                                                    s.raw_dt if raw else s.model_dt)
        emit = {"frames": to_uint8(kept), "actions": model_actions[:l],
                "reread": a_hat[:l] * std + mean, "states": states[r - 1::r], "u": u, "u_raw": u_raw,
                "done": done}
        robot = carry.robot
        if s.state_dim:  # the robot's state at each kept frame, read off the frame its action produced
            robots = state_head.unroll(norm[4], carry.robot, model_actions[:l], jnp.moveaxis(kept, 1, 0))
            robot, emit["robot_states"] = robots[-1], robots
        new = Carry(jnp.where(done, carry.context, context), jnp.where(done, carry.state, state), done,
                    carry.chunk + 1, jnp.where(done, carry.robot, robot), carry.anchor)
        return new, emit


# ================================================================================================================
# Batched drivers: scan (JAX policy or recorded actions) and host loop (any HostPolicy)
# ================================================================================================================
class Rollout:
    """Rollouts of one world model (config + normalisation stats) over batches of initial conditions.

    ``run`` (scan, JAX policy), ``run_host`` (Python loop, host policy), ``run_offline`` (recorded actions) all return
    a dict of numpy arrays, B episodes, N chunks, l kept frames per chunk::

        frames uint8 [B, V, N*l, H, W, 3]   predicted frames kept per chunk (invalid ones after termination too)
        initial_frames uint8 [B, V, K, H, W, 3]
        actions float32 [B, N*l, A]         commanded raw actions a[0:l] of every chunk
        reread  float32 [B, N*l, A]         raw actions re-read by the inverse mode
        states  float32 [B, N*l, A]         imagined state after each commanded action (delta_ee: the pose)
        robot_states float32 [B, N*l, S]    the learned robot state at each kept frame (world models with one)
        u float32 [B, N], done bool [B, N]  U_chunk (normalised units) and done' after each chunk; valid = ~done
        u_raw float32 [B, N]                the same mean L2 distance in raw action units
        tau_units str                       which of the two decided termination (rollout.tau_units)
        frame_valid bool [B, N*l], terminated_at int32 [B] (-1 never), termination_rate float, tau float
    """

    def __init__(self, cfg: Config, norm_stats, mesh=None, *, data_fps: float, num_chunks: int | None = None,
                 cache: bool = True, state_reader=None, head=None):
        """``data_fps``: the frame rate of the world model's data (``checkpoint.read_robot(path).fps``); its action
        space is its norm stats'. ``head``: the world model's learned state (``state_head.load``; None: policies see
        the imagined commanded state)."""
        self.cfg = cfg
        self.spec = make_spec(cfg, data_fps, num_chunks, action_space=norm_stats.action_space,
                              state_dim=state_head.state_dim(head))
        self.tau = resolve_tau(cfg.rollout.tau)  # what run / run_host use by default
        if state_reader is not None and self.spec.action_space.kind != "delta_ee":
            raise UserError(f"a state reader sets the gripper entry of an end-effector pose; this world model's "
                            f"actions are {self.spec.action_space.kind}")
        self.mesh = mesh if mesh is not None else sharding.make_mesh(MeshConfig(-1, 1, 1))
        self._batch = sharding.batch_sharding(self.mesh)
        self._repl = sharding.replicated(self.mesh)
        self.batch_multiple = self.mesh.shape["data"] * self.mesh.shape["fsdp"]
        self.norm = jax.device_put((*norm_stats.arrays(), head), self._repl)
        self.chunk_fns, self._init, self._observe, self._model_step_fn, self._scan_policy, self._scan_actions = \
            _compiled(cfg.model, cfg.flow, self.spec, cache, state_reader and state_reader.apply)
        # context-parallel attention traces under the mesh; a no-op for meshes without a "context" axis
        self._init, self._observe, self._model_step_fn, self._scan_policy, self._scan_actions = (
            sharding.bind_mesh(f, self.mesh) for f in (self._init, self._observe, self._model_step_fn,
                                                       self._scan_policy, self._scan_actions))
        # state_reader: anything with a pure ``apply(params, images uint8 [V, H, W, 3]) -> gripper width`` and
        # ``params`` (e.g. ``benchmarks.bussing.scorers.PerceptionScorer.state_reader()``); see ``ChunkFns.observe``
        self.reader_params = None if state_reader is None else jax.device_put(state_reader.params, self._repl)
        # wall seconds spent inside the jitted programs (first calls' compiles included; a host policy's own time
        # between chunk steps is not): what share of a sweep the world model itself costs
        self.compiled_seconds = 0.0

    def _call(self, fn, *args, fetch: bool = True):
        """``fn(*args)``, finished (and fetched to the host unless ``fetch=False``), its wall time added to
        ``compiled_seconds``."""
        t = time.perf_counter()
        out = fn(*args)
        out = jax.device_get(out) if fetch else jax.block_until_ready(out)
        self.compiled_seconds += time.perf_counter() - t
        return out

    def _model_step(self, params, carry, actions, keys, tau):
        return self._model_step_fn(params, self.norm, carry, actions, keys, tau)

    # -- placement ---------------------------------------------------------------------------------------------
    def place_params(self, params):
        axes = dit.param_axes(self.cfg.model, self.chunk_fns.tok.token_dim, self.chunk_fns.grid)
        shard = jax.tree.map(lambda ax, x: sharding.named(self.mesh, ax, x.shape), axes, params,
                             is_leaf=lambda a: type(a) is tuple)
        return jax.device_put(params, shard)

    def _pad(self, x: np.ndarray, n: int) -> jax.Array:
        x = np.asarray(x)
        if x.shape[0] < n:
            x = np.concatenate([x, np.repeat(x[-1:], n - x.shape[0], 0)], 0)
        return jax.device_put(x, self._batch)

    def _inputs(self, ics: InitialConditions, keys):
        """(B, frames, (imagined commanded state, learned robot state), task, keys), padded to the mesh's batch."""
        s = self.spec
        want = (s.views, s.context, *s.image_size, 3)
        if tuple(np.shape(ics.frames)[1:]) != want:
            raise UserError(f"initial frames [B, views, K, H, W, 3] = {list(np.shape(ics.frames))}, the world model "
                            f"takes [B, {', '.join(map(str, want))}] (data.views, data.context_frames, "
                            f"data.image_size)")
        if np.shape(ics.state)[1:] != (s.action_dim,):
            raise UserError(f"initial state {list(np.shape(ics.state))}, the world model's imagined state is "
                            f"[B, {s.action_dim}] ({s.action_space.kind} actions)")
        B = np.shape(ics.frames)[0]
        robot = np.zeros((B, 0), np.float32) if ics.robot is None else np.asarray(ics.robot, np.float32)
        if robot.shape[1:] != (s.state_dim,):
            raise UserError(f"initial robot state {list(robot.shape)}, the world model's learned state is "
                            f"[B, {s.state_dim}]" + (" (an episode store that records the state, or an .npz with "
                                                     "robot [B, S])" if s.state_dim else " (it has none)"))
        n = -(-B // self.batch_multiple) * self.batch_multiple
        frames, state = self._pad(ics.frames, n), (self._pad(np.asarray(ics.state, np.float32), n), self._pad(robot, n))
        task, keys = self._pad(np.asarray(ics.task, np.int32), n), self._pad(np.asarray(keys), n)
        return B, frames, state, task, keys

    # -- scan paths ----------------------------------------------------------------------------------------------
    def run(self, params, policy: JaxPolicy, ics: InitialConditions, keys, tau: float | None = None) -> dict:
        """Closed loop, the whole episode in one jitted ``lax.scan``; ``keys`` from :func:`episode_keys`."""
        self._check_chunk(policy.chunk, policy.name)
        self.check_policy(policy)
        tau = self.tau if tau is None else tau
        B, frames, state, task, keys = self._inputs(ics, keys)
        params, policy_params = self.place_params(params), jax.device_put(policy.params, self._repl)
        emits = self._call(self._scan_policy, policy.apply, params, self.norm, policy_params, self.reader_params,
                           frames, state, task, keys, jnp.float32(tau))
        return self._finish(emits, ics, B, tau, chunk_axis=0)

    def run_offline(self, params, ics: InitialConditions, actions, keys, tau: float = math.inf) -> dict:
        """Open loop: ``actions`` raw [B, N, >= l', A] (the recorded actions of each chunk, :func:`chunk_actions`)
        replace the policy. Scoring the frames against the recorded ones is the caller's (``measures.metrics``)."""
        actions = np.asarray(actions, np.float32)
        if actions.ndim != 4 or actions.shape[1] != self.spec.num_chunks or actions.shape[2] < self.spec.predict \
                or actions.shape[3] != self.spec.action_dim:
            raise ValueError(f"actions {list(actions.shape)}: expected [B, {self.spec.num_chunks}, "
                             f">={self.spec.predict}, {self.spec.action_dim}]")
        B, frames, state, task, keys = self._inputs(ics, keys)
        emits = self._call(self._scan_actions, self.place_params(params), self.norm, frames, state, task, keys,
                           jnp.float32(tau), self._pad(actions, len(keys)))
        return self._finish(emits, ics, B, tau, chunk_axis=0)

    # -- host loop ---------------------------------------------------------------------------------------------
    def run_host(self, params, policy, ics: InitialConditions, keys, tau: float | None = None,
                 progress: bool = False, skip_done: bool = False) -> dict:
        """Closed loop from Python: per chunk, the jitted ``observe`` -> ``policy.infer`` on the host for every
        episode -> the jitted model step. A JaxPolicy is wrapped with ``as_host``; a host policy whose ``infer``
        takes ``rng`` gets the same per-chunk key as the scan, so both paths agree. ``skip_done=True`` does not query
        the policy for finished episodes (saves remote calls; their later, invalid chunks then differ from ``run``)."""
        self.check_policy(policy)
        if isinstance(policy, JaxPolicy):
            policy = as_host(policy)
        self._check_chunk(policy.chunk, type(policy).__name__)
        takes_rng = "rng" in inspect.signature(policy.infer).parameters
        tau = self.tau if tau is None else tau
        B, frames, state, task, keys = self._inputs(ics, keys)
        params = self.place_params(params)
        carry = self._call(self._init, frames, *state, fetch=False)
        emits = []
        chunks = range(self.spec.num_chunks)
        if progress:
            from tqdm import tqdm
            chunks = tqdm(chunks, desc="rollout chunks", unit="chunk")
        for _ in chunks:
            obs, k_pol = self._call(self._observe, carry, task, keys, self.reader_params)
            done = np.asarray(jax.device_get(carry.done))
            A = self.spec.action_dim
            acts = np.zeros((len(k_pol), self.spec.step_actions, A), np.float32)
            for b in range(B):  # padded episodes copy episode B-1: reuse its actions
                if skip_done and done[b]:
                    continue
                ob = {k: v[b] for k, v in obs.items()}
                a = policy.infer(ob, rng=jax.random.wrap_key_data(k_pol[b])) if takes_rng else policy.infer(ob)
                a = np.asarray(a, np.float32)
                if a.ndim != 2 or a.shape[0] < self.spec.executed or a.shape[1] != A:
                    raise UserError(f"policy {type(policy).__name__} returned actions of shape {list(a.shape)}, "
                                    f"the world model takes [>={self.spec.executed}, {A}] "
                                    f"({self.spec.action_space.kind} actions)")
                acts[b] = fill_chunk(a[:self.spec.step_actions], self.spec.step_actions)
            acts[B:] = acts[B - 1]
            carry, emit = self._call(self._model_step, params, carry, self._pad(acts, len(acts)), keys,
                                     jnp.float32(tau), fetch=False)
            emits.append(jax.device_get(emit))
        stacked = {k: np.stack([e[k] for e in emits]) for k in emits[0]}
        return self._finish(stacked, ics, B, tau, chunk_axis=0)

    # -- helpers -----------------------------------------------------------------------------------------------
    def check_policy(self, policy) -> None:
        """One-line UserError, before anything compiles, when ``policy`` declares other action / state dimensions
        than this world model's; a JaxPolicy's output shape is also traced (``jax.eval_shape``, nothing runs)."""
        s = self.spec
        name = getattr(policy, "name", None) or type(policy).__name__
        seen = s.state_dim or s.action_dim  # the state a policy is handed
        try:
            check_dims(policy, s.action_dim, seen, name,
                       f"the world model ({s.action_space.kind} actions, model.action_dim"
                       + (f"; the robot's {s.state_dim}-D learned state)" if s.state_dim else ")"))
        except UserError as e:  # a policy of the commands' own space: say the flag that hands it that state
            if s.state_dim and getattr(policy, "state_dim", None) == s.action_dim:
                raise UserError(f"{e}: --no-learned-state hands it the integrated commands ({s.action_dim}-D) "
                                "instead") from None
            raise
        need = getattr(policy, "min_views", None)  # an openpi mapping's cameras (ALOHA: 4)
        if need is not None and s.views < need:
            raise UserError(f"policy {name!r} reads {need} views (its mapping's min_views), the world model has "
                            f"{s.views} (data.views)")
        if isinstance(policy, JaxPolicy):
            obs = {"images": jax.ShapeDtypeStruct((s.views, *s.image_size, 3), jnp.uint8),
                   "state": jax.ShapeDtypeStruct((seen,), jnp.float32),
                   "task": jax.ShapeDtypeStruct((), jnp.int32)}
            try:
                out = jax.eval_shape(policy.apply, policy.params, obs, jax.random.key(0))
            except (TypeError, ValueError) as e:  # e.g. a matmul sized for another state: say which sides
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise UserError(f"policy {name!r} cannot take this world model's observation (images "
                                f"[{s.views}, {s.image_size[0]}, {s.image_size[1]}, 3], state [{seen}]): "
                                f"{first}") from e
            if len(out.shape) != 2 or out.shape[1] != s.action_dim:
                raise UserError(f"policy {name!r} returns actions of shape {list(out.shape)}, the world model takes "
                                f"[chunk, {s.action_dim}] ({s.action_space.kind} actions, model.action_dim)")

    def _check_chunk(self, chunk: int, name: str):
        if chunk < self.spec.executed:
            raise ValueError(f"policy {name} proposes {chunk} actions per call; a chunk of this rollout executes "
                             f"{self.spec.executed} (rollout.keep_frames x policy_hz / control_hz)")

    def _finish(self, emits: dict, ics: InitialConditions, B: int, tau: float, chunk_axis: int) -> dict:
        """[N, Bpad, ...] per-chunk emissions -> the documented [B, ...] episode arrays."""
        s = self.spec
        e = {k: np.moveaxis(np.asarray(v), chunk_axis, 1)[:B] for k, v in emits.items()}  # [B, N, ...]
        frames = e["frames"]  # [B, N, V, l, H, W, 3]
        frames = np.moveaxis(frames, 2, 1).reshape(B, s.views, s.num_frames, *frames.shape[-3:])
        flat = lambda x: x.reshape(B, s.num_frames, *x.shape[3:])  # noqa: E731  [B, N, l, ...] -> [B, N*l, ...]
        done = e["done"].astype(bool)
        actions, reread = flat(e["actions"]), flat(e["reread"])
        extra = {"robot_states": flat(e["robot_states"])} if "robot_states" in e else {}
        return {**extra, "frames": frames, "initial_frames": np.asarray(ics.frames), "actions": actions,
                "reread": reread, "states": flat(e["states"]), "u": e["u"].astype(np.float32),
                "u_raw": e["u_raw"].astype(np.float32), "tau_units": s.tau_units,
                "done": done, "frame_valid": np.repeat(~done, s.keep, axis=1),
                "terminated_at": np.where(done.any(-1), done.argmax(-1), -1).astype(np.int32),
                "termination_rate": float(done.any(-1).mean()), "tau": float(tau)}


# ================================================================================================================
# The jitted programs, shared by every Rollout with the same (model config, flow config, spec, cache flag)
# ================================================================================================================
@functools.lru_cache(maxsize=32)
def _compiled(model_cfg, flow_cfg, spec: RolloutSpec, cache: bool, reader=None):
    st = ChunkFns(model_cfg, flow_cfg, spec, cache)
    observe_b = jax.vmap(lambda c, t, k, rp: st.observe(c, t, k, rp, reader), in_axes=(0, 0, 0, None))
    step_b = jax.vmap(st.model_step, in_axes=(None, None, 0, 0, 0, None))
    step_offline = jax.vmap(functools.partial(st.model_step, raw=False), in_axes=(None, None, 0, 0, 0, None))

    def scan_policy(policy_apply, params, norm, policy_params, reader_params, frames, state, task, keys, tau):
        act = lambda o, k: policy_apply(policy_params, o, jax.random.wrap_key_data(k))  # noqa: E731

        def body(carry, _):
            obs, k_pol = observe_b(carry, task, keys, reader_params)
            return step_b(params, norm, carry, fill_chunk(jax.vmap(act)(obs, k_pol), spec.raw_needed), keys, tau)

        return jax.lax.scan(body, jax.vmap(st.init)(frames, *state), None, length=spec.num_chunks)[1]

    def scan_actions(params, norm, frames, state, task, keys, tau, actions):
        body = lambda carry, a: step_offline(params, norm, carry, a, keys, tau)  # noqa: E731
        return jax.lax.scan(body, jax.vmap(st.init)(frames, *state), jnp.swapaxes(actions, 0, 1))[1]

    return (st, jax.jit(jax.vmap(st.init)), jax.jit(observe_b), jax.jit(step_b),
            jax.jit(scan_policy, static_argnums=(0,)), jax.jit(scan_actions))


# ================================================================================================================
# Initial conditions and recorded actions from an episode store
# ================================================================================================================
def from_episode(ep, views, spec: RolloutSpec, start: int = 0, task: int = 0):
    """(initial conditions of one episode [no batch axis], recorded raw actions [N, l', A], recorded frames
    [V, N*l, H, W, 3]) for an offline rollout starting at frame ``start``. Rollout step i (i = 0 is the last
    context frame) is episode frame ``start + stride * (K - 1 + i)``; its action is the composition of the
    ``stride`` recorded actions in between (:func:`chunk_actions`)."""
    s = spec
    frame_at = lambda i: start + s.stride * (s.context - 1 + i)  # noqa: E731
    if max_offline_chunks(ep.length, s, start) < s.num_chunks:
        raise ValueError(f"episode {ep.episode_id}: {ep.length} frames are too few for an offline rollout of "
                         f"{s.num_chunks} chunks at stride {s.stride} from frame {start}; at most "
                         f"{max_offline_chunks(ep.length, s, start)} (max_offline_chunks)")
    ctx_idx = [frame_at(i) for i in range(-(s.context - 1), 1)]
    frames = np.stack([np.asarray(ep.frames[v])[ctx_idx] for v in views])
    actions = chunk_actions(np.asarray(ep.actions)[frame_at(0):], s)
    tgt_idx = [frame_at(i) for i in range(1, s.num_frames + 1)]
    targets = np.stack([np.asarray(ep.frames[v])[tgt_idx] for v in views])
    return (frames, initial_state(ep, s, frame_at(0)), np.int32(task)), actions, targets


def initial_state(ep, spec: RolloutSpec, t: int) -> np.ndarray:
    """float32 [A]: the imagined state a rollout starting at frame ``t`` of episode ``ep`` begins from (what was
    measured there: delta_ee the end-effector pose, else the recorded state where it has the action's dimension;
    ``ActionSpace.initial_state``)."""
    return spec.action_space.initial_state(ep.actions, ep.ee_pose, getattr(ep, "state", None), t)


def chunk_actions(actions: np.ndarray, spec: RolloutSpec) -> np.ndarray:
    """Recorded raw actions [T, A] at the data rate, from the last context frame on -> the model-rate actions of
    every chunk [N, l', A] (``stride`` recorded actions composed into one, ``pipeline.compose_actions``); after the
    recording ends the robot holds still (``ActionSpace.hold``: delta_ee zero motion with the last gripper command,
    absolute the last target)."""
    from sc3_jax.data.pipeline import compose_actions
    r = spec.stride  # recorded (data-rate) actions per model step
    need = ((spec.num_chunks - 1) * spec.keep + spec.predict) * r
    a = np.asarray(actions, np.float32)
    spec.action_space.check(a, "recorded actions")
    if len(a) < need:
        a = np.concatenate([a, spec.action_space.hold(a[-1], need - len(a))])
    model_rate = np.stack([compose_actions(a, i * r, r, spec.action_space) for i in range(need // r)])
    return np.stack([model_rate[c * spec.keep: c * spec.keep + spec.predict] for c in range(spec.num_chunks)])


def recorded_targets(frames: np.ndarray, spec: RolloutSpec) -> tuple[np.ndarray, np.ndarray]:
    """Recorded frames [V, T, ...] from the last context frame on -> (the frames at the model's steps [V, N*l, ...],
    valid bool [N*l]: before the recording ended), what an offline rollout's frames are compared with."""
    idx = spec.stride * np.arange(1, spec.num_frames + 1)
    valid = idx < frames.shape[1]
    return frames[:, np.minimum(idx, frames.shape[1] - 1)], valid


def max_offline_chunks(length: int, spec: RolloutSpec, start: int = 0) -> int:
    """The most chunks an episode of ``length`` frames supports from ``start`` (see :func:`from_episode`)."""
    s = spec
    frame_at = lambda i: start + s.stride * (s.context - 1 + i)  # noqa: E731
    n = 0  # chunk n+1 needs the actions of steps < n*l + l' (frames up to frame_at(n*l + l') - 1) and its targets
    while frame_at(n * s.keep + s.predict) <= length and frame_at((n + 1) * s.keep) < length:
        n += 1
    return n


def stack_initial_conditions(items) -> InitialConditions:
    """(frames, state, task[, robot state]) per condition -> InitialConditions (robot None when none is given)."""
    frames, state, task, *robot = zip(*items)
    robot = np.stack(robot[0]).astype(np.float32) if robot and robot[0][0] is not None else None
    return InitialConditions(np.stack(frames), np.stack(state).astype(np.float32), np.asarray(task, np.int32), robot)
