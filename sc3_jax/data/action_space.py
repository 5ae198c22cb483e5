"""What a robot's actions mean: the action space a dataset declares (``dataset.json`` ``"action_space"``) and the few
operations that depend on it. Numpy only; ``sc3_jax/rollout/imagination_state.py`` holds the jnp twins rollouts run.

Kinds (``kind``):

- ``delta_ee``: ``(dx, dy, dz, axis-angle rx, ry, rz, gripper target)`` [7], the simulated benchmark's. Composed:
  xyz summed, rotations chained with later ones on the left (world frame), the last gripper target. Imagined state:
  the end-effector pose ``(x, y, z, rotvec, gripper)`` integrated from the episode's ``ee_pose`` (from zero motion
  at the window's first frame when the dataset recorded none). Pseudo-actions from consecutive measured poses.
- ``absolute``: position targets of any dimension (joints or end-effector coordinates; a bimanual ALOHA: 14 joint
  targets). Composed: the last target. Imagined state: the last target (what the robot is driven to).
- ``velocity``: rates of any dimension. Composed: the mean. Imagined state: ``state + gain * action * dt`` at ``dt``
  seconds per action, from the *measured* quantity each dimension moves: ``measured[i]`` is the index of the
  recorded ``state`` entry that dimension i drives (SO-101's dx drives ee_x), ``gain[i]`` its state units per action
  unit per second; both stated at import (``dataset.json``) or fitted from the recorded data (:func:`fit_measured`,
  by ``NormStats.from_store``) and saved with the model in ``norm_stats.json``. Without a mapping, a recorded state of
  the action's own dimension is the measurement; with neither, the commands integrate from zero (a displacement
  since the window's start: nothing tells the model where the arm is). ``targets`` lists dimensions that are
  position targets instead (e.g. DROID's gripper): composed and imagined as in ``absolute``.

``low`` / ``high`` (velocity only; set from the data by ``NormStats.from_store``): the range the imagined state
took in the recordings; every integration step is clipped to it, in training windows and rollouts alike, so a
rollout's commanded state never leaves what training showed.

The imagined state always lives in the action's own space (``dim`` values named ``state_names``), each dimension in
the units of what it moves, so the model's pose condition and the state a policy observes inside an imagined
rollout both have the action's dimension. Pseudo-actions exist only where a real end-effector pose was measured
(``delta_ee`` with ``ee_pose``); every other case is refused in one line (``pseudo_refusal``).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from sc3_jax.data import rotations
from sc3_jax.core.errors import UserError

KINDS = ("delta_ee", "absolute", "velocity")
DELTA_EE_NAMES = ("dx", "dy", "dz", "rx", "ry", "rz", "gripper")
POSE_NAMES = ("x", "y", "z", "rx", "ry", "rz", "gripper")
GRIPPER = 6  # the gripper entry of a delta_ee action and of an end-effector pose


@dataclasses.dataclass(frozen=True)
class ActionSpace:
    kind: str = "delta_ee"
    dim: int = 7
    names: tuple[str, ...] = ()  # one per dimension; () = defaults (DELTA_EE_NAMES, or a0, a1, ...)
    targets: tuple[int, ...] = ()  # velocity only: dimensions that are position targets (a gripper)
    measured: tuple[int, ...] = ()  # velocity only: per dimension the recorded-state entry it moves (-1: none)
    gain: tuple[float, ...] = ()  # velocity only: per dimension, state units per action unit per second (() = 1)
    low: tuple[float, ...] = ()  # the imagined state's recorded range, per dimension (() = unclipped)
    high: tuple[float, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(str(n) for n in self.names) or _default_names(self.kind, self.dim))
        for f in ("targets", "measured"):  # indices: whole numbers (1.5 or true read as 1 once, silently)
            v = getattr(self, f)
            if any(isinstance(i, bool) or not isinstance(i, (int, np.integer, float))
                   or (isinstance(i, float) and not (np.isfinite(i) and i == int(i))) for i in v):
                raise UserError(f"action_space.{f} {list(v)[:8]}: whole-number indices")
            object.__setattr__(self, f, tuple(int(i) for i in v))
        for f in ("gain", "low", "high"):
            object.__setattr__(self, f, tuple(float(x) for x in getattr(self, f)))
        if self.kind not in KINDS:
            raise UserError(f"action_space.kind {self.kind!r}: one of {', '.join(KINDS)}")
        if int(self.dim) < 1:
            raise UserError(f"action_space.dim {self.dim}: must be a positive number of action dimensions")
        object.__setattr__(self, "dim", int(self.dim))
        if self.kind == "delta_ee" and self.dim != 7:
            raise UserError(f"action_space: delta_ee actions are 7-D (xyz, rotation vector, gripper), this one is "
                            f"{self.dim}-D; declare kind 'absolute' or 'velocity'")
        if len(self.names) != self.dim:
            raise UserError(f"action_space.names: {len(self.names)} names for {self.dim} dimensions")
        if self.targets and self.kind != "velocity":
            raise UserError(f"action_space.targets: only velocity actions have target dimensions, not {self.kind}")
        if any(not 0 <= i < self.dim for i in self.targets):
            raise UserError(f"action_space.targets {list(self.targets)}: indices must lie in [0, {self.dim})")
        if (self.measured or self.gain) and self.kind != "velocity":
            raise UserError(f"action_space.measured/gain: only velocity actions integrate into a measurement, not "
                            f"{self.kind}")
        for f in ("measured", "gain", "low", "high"):
            v = getattr(self, f)
            if v and len(v) != self.dim:
                raise UserError(f"action_space.{f}: {len(v)} values for {self.dim} dimensions")
        if any(i < -1 for i in self.measured):
            raise UserError(f"action_space.measured {list(self.measured)}: state indices, or -1 for none")
        if bool(self.low) != bool(self.high):
            raise UserError("action_space: low and high come together")
        if not all(np.isfinite(self.gain)) or (self.low and not np.all(np.less_equal(self.low, self.high))):
            raise UserError(f"action_space: gain {list(self.gain)}, low {list(self.low)}, high {list(self.high)}: "
                            "finite gains and low <= high")

    # -- the declaration ---------------------------------------------------------------------------------------
    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the imagined state's dimensions (the action's own space; a pose for delta_ee)."""
        return POSE_NAMES if self.kind == "delta_ee" else self.names

    @property
    def gains(self) -> np.ndarray:
        """float32 [dim]: state units per action unit per second (1 where none was stated or fitted)."""
        return np.asarray(self.gain or (1.0,) * self.dim, np.float32)

    def clip(self, x):
        """``x`` [..., dim] (numpy or jnp) clipped to the recorded range, where one is set."""
        if not self.low:
            return x
        xp = np if isinstance(x, np.ndarray) else _jnp()
        return xp.clip(x, xp.asarray(self.low, x.dtype), xp.asarray(self.high, x.dtype))

    def to_dict(self) -> dict:
        d = {"kind": self.kind, "dim": self.dim, "names": list(self.names)}
        for f in ("targets", "measured", "gain", "low", "high"):
            if getattr(self, f):
                d[f] = list(getattr(self, f))
        return d

    @classmethod
    def from_dict(cls, d: dict | None, dim: int | None = None, where: str = "action_space") -> ActionSpace:
        """A declaration as written by ``to_dict``; None (stores and stats files from before declarations) is the
        simulated benchmark's delta_ee 7-D space. ``dim`` (e.g. dataset.json's ``action_dim``) must agree."""
        if d is None:
            space = cls()
        else:
            if not isinstance(d, dict) or "kind" not in d:
                raise UserError(f"{where}: expected {{\"kind\": ..., \"dim\": ..., \"names\": [...]}}, got {d!r}")
            unknown = set(d) - set(FIELDS)
            if unknown:
                raise UserError(f"{where}: unknown keys {sorted(unknown)} ({', '.join(FIELDS)})")
            try:
                space = cls(d["kind"], int(d.get("dim", dim if dim is not None else len(d.get("names", ())))),
                            *(tuple(d.get(f, ())) for f in FIELDS[2:]))
            except (TypeError, ValueError) as e:
                raise UserError(f"{where}: {e}") from None
        if dim is not None and space.dim != dim:
            raise UserError(f"{where}: declares {space.dim}-D actions, action_dim is {dim}")
        return space

    def same_kind(self, other: ActionSpace) -> bool:
        """Whether actions of ``other`` mean what these mean (names aside: they only label the dimensions; the
        measurement they integrate into and its range are facts of the data, fitted again from another store)."""
        return (self.kind, self.dim, self.targets) == (other.kind, other.dim, other.targets)

    def conditioned(self, other: ActionSpace) -> bool:
        """Whether a model of ``other``'s statistics is told where the arm is the way these would tell it."""
        return self.same_kind(other) and (self.measured, self.gain) == (other.measured, other.gain)

    def check(self, actions: np.ndarray, what: str = "actions") -> None:
        if np.ndim(actions) < 1 or np.shape(actions)[-1] != self.dim:
            raise ValueError(f"{what} of shape {list(np.shape(actions))}: this {self.kind} action space is "
                             f"{self.dim}-D")

    # -- composing actions ---------------------------------------------------------------------------------------
    def compose(self, actions: np.ndarray) -> np.ndarray:
        """The single action equivalent to ``actions`` [k, dim] applied in turn (float32 [dim])."""
        self.check(actions)
        a = np.asarray(actions, np.float64)
        if self.kind == "delta_ee":
            return _compose_delta_ee(a)
        if self.kind == "absolute":
            return a[-1].astype(np.float32)
        out = a.mean(0)
        out[list(self.targets)] = a[-1, list(self.targets)]
        return out.astype(np.float32)

    def hold(self, last: np.ndarray, n: int) -> np.ndarray:
        """float32 [n, dim]: the actions that keep the robot where ``last`` left it (after a recording ends)."""
        last = np.asarray(last, np.float32)
        if self.kind == "absolute":
            return np.repeat(last[None], n, 0)
        out = np.zeros((n, self.dim), np.float32)
        keep = [GRIPPER] if self.kind == "delta_ee" else list(self.targets)
        out[:, keep] = last[keep]
        return out

    # -- the imagined state --------------------------------------------------------------------------------------
    def integrate(self, state: np.ndarray, actions: np.ndarray, dt: float = 1.0) -> np.ndarray:
        """float32 [n + 1, dim]: ``state`` and the imagined state after each of ``actions`` [n, dim]; ``dt``: seconds
        per action (velocity only). The numpy twin of ``imagination_state.frame_poses``."""
        self.check(actions)
        if self.kind == "delta_ee":
            return _integrate_delta_ee(state, actions)
        state, actions = np.asarray(state, np.float64), np.asarray(actions, np.float64)
        if self.kind == "absolute":
            return np.concatenate([state[None], actions]).astype(np.float32)
        out, s, g, tg = [state.astype(np.float32)], state.astype(np.float32), self.gains, list(self.targets)
        for a in actions.astype(np.float32):  # step by step, as rollouts do: each step is clipped to the range
            s = s + g * a * np.float32(dt)
            s[tg] = a[tg]
            s = self.clip(s)
            out.append(s)
        return np.stack(out).astype(np.float32)

    def start_state(self, actions: np.ndarray, ee_pose: np.ndarray | None, state: np.ndarray | None,
                    t: int) -> np.ndarray:
        """The state condition at frame ``t`` of a recorded episode (training windows): the measured state with the
        commands in force (at t = 0 none was given yet)."""
        if self.kind == "delta_ee":
            p = (np.asarray(ee_pose[t], np.float32).copy() if ee_pose is not None
                 else _pose_origin(actions, t))
            if t > 0:
                p[GRIPPER] = actions[t - 1, GRIPPER]
            return p
        if self.kind == "absolute":
            if t > 0:
                return np.asarray(actions[t - 1], np.float32).copy()
            return self._measured(actions, state, 0)
        s = self._measured(actions, state, t)
        if t > 0:
            s[list(self.targets)] = actions[t - 1, list(self.targets)]
        return s

    def initial_state(self, actions: np.ndarray, ee_pose: np.ndarray | None, state: np.ndarray | None,
                      t: int) -> np.ndarray:
        """The state an imagined rollout starting at frame ``t`` of a recorded episode begins from: what was
        measured there (delta_ee: the pose; otherwise the recorded state where it has the action's dimension)."""
        if self.kind == "delta_ee":
            return np.asarray(ee_pose[t], np.float32) if ee_pose is not None else _pose_origin(actions, t)
        if state is not None and np.shape(state)[-1] == self.dim:
            return np.asarray(state[t], np.float32)
        return self.start_state(actions, ee_pose, state, t)

    def _measured(self, actions, state, t: int) -> np.ndarray:
        if self.measured and state is not None:  # each dimension's own measurement (SO-101: dx -> ee_x)
            s = np.zeros(self.dim, np.float32)
            for i, j in enumerate(self.measured):
                if j >= 0:
                    s[i] = state[t, j]
            s[list(self.targets)] = actions[0, list(self.targets)]  # before any command: the first target
            return self.clip(s)
        if state is not None and np.shape(state)[-1] == self.dim:
            return np.asarray(state[t], np.float32).copy()
        if self.kind == "absolute":  # no matching measurement: the first target stands in for it
            return np.asarray(actions[0], np.float32).copy()
        # velocities of something the robot does not record: the commands integrate from zero, a displacement since
        # the window's (the rollout's) start (state a mapping, or record the quantity, to tell the model more)
        s = np.zeros(self.dim, np.float32)
        s[list(self.targets)] = actions[0, list(self.targets)]
        return s

    def state_series(self, actions: np.ndarray, ee_pose: np.ndarray | None,
                     state: np.ndarray | None, dt: float = 1.0) -> np.ndarray | None:
        """The recorded values the imagined state takes (its normalisation statistics and range come from them):
        the poses, the targets, or the measured entries; None where nothing was recorded (delta_ee without a pose).
        ``dt``: seconds per recorded action (the displacement of velocities that move nothing recorded)."""
        if self.kind == "delta_ee":
            return ee_pose
        a = np.asarray(actions, np.float64)
        if self.kind == "absolute":
            return a
        if self.measured and state is not None:
            s = np.zeros(a.shape)
            for i, j in enumerate(self.measured):
                if j >= 0:
                    s[:, i] = np.asarray(state, np.float64)[:, j]
                elif i not in self.targets:  # moves nothing recorded: its displacement since the start
                    s[:, i] = np.cumsum(a[:, i] * self.gains[i] * dt)
        elif state is None or np.shape(state)[-1] != self.dim:  # the displacement since the start (see _measured)
            s = np.cumsum(a * self.gains * dt, axis=0)
        else:
            s = np.array(state, np.float64)
        s[:, list(self.targets)] = a[:, list(self.targets)]
        return s

    def with_range(self, low, high) -> ActionSpace:
        """This space with its integrated state clipped to [low, high]: velocities only (targets are what the
        policy sends, and a delta_ee pose's rotation wraps)."""
        if self.kind != "velocity":
            return self
        return dataclasses.replace(self, low=tuple(np.asarray(low, float)), high=tuple(np.asarray(high, float)))

    # -- pseudo-actions ------------------------------------------------------------------------------------------
    def pseudo_refusal(self, has_pose: bool) -> str | None:
        """Why this data cannot give pseudo-actions (one line), or None when it can."""
        if self.kind != "delta_ee":
            return (f"pseudo-actions come from measured end-effector poses of delta_ee actions; these actions are "
                    f"{self.kind}: set data.pseudo_action_prob 0")
        if not has_pose:
            return "pseudo-actions need the measured end-effector pose (ee_pose), this dataset has none: " \
                   "set data.pseudo_action_prob 0"
        return None

    def pseudo(self, ee_pose: np.ndarray | None, frame_indices: np.ndarray,
               actions: np.ndarray | None = None) -> np.ndarray:
        """Actions between consecutive given frames from measured poses: float32 [len(frame_indices) - 1, 7].
        The gripper entry is the command in force at the end of each interval, ``actions[t_next - 1, 6]`` (the one
        meaning the gripper entry has everywhere); without ``actions`` the measured gap ``ee_pose[t_next, 6]``
        stands in for it (data that recorded no commands)."""
        refusal = self.pseudo_refusal(ee_pose is not None)
        if refusal:
            raise UserError(refusal)
        idx = np.asarray(frame_indices)
        p = np.asarray(ee_pose, np.float64)[idx]
        out = np.empty((len(p) - 1, 7))
        out[:, :3] = p[1:, :3] - p[:-1, :3]
        out[:, 3:6] = rotations.relative_rotvec(p[:-1, 3:6], p[1:, 3:6])
        out[:, 6] = p[1:, 6] if actions is None else np.asarray(actions)[idx[1:] - 1, 6]
        return out.astype(np.float32)


FIELDS = ("kind", "dim", "names", "targets", "measured", "gain", "low", "high")
FIT_MIN_R2 = 0.25  # a dimension whose best state entry explains less of its step changes moves nothing recorded
# (SO-101 explains 0.37-0.50: its arm lags, saturates and stops on the table; unrelated entries stay under 0.05)


def fit_measured(space: ActionSpace, episodes, dt: float) -> ActionSpace:
    """``space`` with ``measured`` and ``gain`` fitted from recorded (actions [T, A], state [T, S]) pairs: for each
    velocity dimension, the state entry whose step change ``state[t+1] - state[t]`` a no-intercept line through
    ``action[t] * dt`` explains best (each entry used once, best fits first), and that line's slope; a dimension
    explained below ``FIT_MIN_R2`` moves nothing recorded (-1). Unchanged where it is stated, not velocity, or
    without a recorded state of another dimension."""
    if space.kind != "velocity" or space.measured:
        return space
    x, y = [], []
    for actions, state in episodes:
        if state is None or np.shape(state)[-1] == space.dim or len(actions) < 2:
            continue
        x.append(np.asarray(actions[:-1], np.float64) * dt)
        y.append(np.diff(np.asarray(state, np.float64), axis=0))
    if not x:
        return space
    x, y = np.concatenate(x), np.concatenate(y)  # [N, A], [N, S]
    xx, yy, xy = (x * x).sum(0), (y * y).sum(0), x.T @ y  # [A], [S], [A, S]
    r2 = np.where((xx[:, None] > 0) & (yy[None] > 0), xy ** 2 / np.maximum(xx[:, None] * yy[None], 1e-300), 0.0)
    r2[list(space.targets)] = 0.0
    measured, gain = [-1] * space.dim, [1.0] * space.dim
    for flat in np.argsort(-r2, axis=None):
        i, j = np.unravel_index(flat, r2.shape)
        if r2[i, j] < FIT_MIN_R2:
            break
        if measured[i] == -1 and j not in measured:
            measured[i], gain[i] = int(j), float(xy[i, j] / xx[i])
    if all(m == -1 for m in measured):
        return space
    return dataclasses.replace(space, measured=tuple(measured), gain=tuple(gain))


def _jnp():
    import jax.numpy as jnp  # only rollouts clip jnp arrays; the data pipeline stays numpy-only
    return jnp


def _default_names(kind: str, dim: int) -> tuple[str, ...]:
    return DELTA_EE_NAMES if kind == "delta_ee" and dim == 7 else tuple(f"a{i}" for i in range(int(dim)))


def _pose_origin(actions: np.ndarray, t: int) -> np.ndarray:
    """A pose where none was measured: the origin with the gripper command in force (motion is then relative)."""
    p = np.zeros(7, np.float32)
    p[GRIPPER] = actions[max(t - 1, 0), GRIPPER]
    return p


def _compose_delta_ee(a: np.ndarray) -> np.ndarray:
    out = np.empty(7)
    out[:3] = a[:, :3].sum(0)
    if len(a) == 1:
        out[3:6] = a[0, 3:6]
    else:
        m = np.eye(3)
        for r in a[:, 3:6]:  # later rotations act on the left (world frame)
            m = rotations.rotvec_to_matrix(r) @ m
        out[3:6] = rotations.matrix_to_rotvec(m)
    out[6] = a[-1, 6]
    return out.astype(np.float32)


def _integrate_delta_ee(pose: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """xyz summed, rotations composed on the left, gripper = command. The rotations are converted in two batched
    calls and composed as matrices: per-step conversions cost more than the rest of a training window (a
    data-loading bottleneck on an accelerator)."""
    pose, actions = np.asarray(pose, np.float64), np.asarray(actions, np.float64)
    steps = rotations.rotvec_to_matrix(actions[:, 3:6])  # [n, 3, 3]
    mats = [rotations.rotvec_to_matrix(pose[3:6])]
    for m in steps:
        mats.append(m @ mats[-1])
    out = np.empty((len(actions) + 1, 7))
    out[0] = pose
    out[1:, :3] = pose[:3] + np.cumsum(actions[:, :3], axis=0)
    out[1:, 3:6] = rotations.matrix_to_rotvec(np.stack(mats[1:])) if len(actions) else 0.0
    out[1:, 6] = actions[:, 6]
    return out.astype(np.float32)


def names_of(feature_names, dim: int) -> tuple[str, ...]:
    """``dim`` names from a LeRobot feature's ``names`` (a list, or a dict of one list such as
    ``{"motors": [...]}``); () where they do not name every dimension."""
    if isinstance(feature_names, dict) and len(feature_names) == 1:
        feature_names = next(iter(feature_names.values()))
    if isinstance(feature_names, Sequence) and not isinstance(feature_names, str) and len(feature_names) == dim \
            and all(isinstance(n, str) for n in feature_names):
        return tuple(feature_names)
    return ()


DELTA_EE = ActionSpace()  # the simulated benchmark's, and what stores and stats files without a declaration hold
