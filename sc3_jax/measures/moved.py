"""What a robot's actions move, for any action space: which recorded quantity (an entry of the episode's ``state``,
or of its end-effector ``ee_pose``) each action axis drives, and by how much a command displaces it. ``sc3
diagnose``'s action-following measures (``action_following.py``, ``tracking.py``) compare where the imagined arm
goes with these.

Where the mapping comes from, first that applies:

* delta_ee actions with a recorded pose: dx, dy, dz move the pose's x, y, z;
* the model's action space says (``ActionSpace.measured``: per axis the state entry it moves, -1 none; read with
  ``getattr`` so a space from before the field reads as undeclared);
* the benchmark says (``benchmark.Locators.moves``: action name -> state name);
* velocity or absolute actions with a recorded state of their own dimension: axis i moves entry i;
* else nothing: the arm is then read in pixels only (``action_following.fit_image_map``).

numpy only."""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Moved:
    """``axes[k]`` moves entry ``entries[k]`` of ``source`` ("state" | "ee_pose"); ``pose``: the entries that are the
    arm's position (those of axes that are not gripper-like targets), named ``names``; ``how``: where it came from."""
    source: str | None = None
    axes: tuple[int, ...] = ()
    entries: tuple[int, ...] = ()
    pose: tuple[int, ...] = ()
    names: tuple[str, ...] = ()
    how: str = "nothing says what the actions move"

    def entry_of(self, axis: int) -> int | None:
        return self.entries[self.axes.index(axis)] if axis in self.axes else None


def moved(space, store, moves_by_name=None) -> Moved:
    """The :class:`Moved` of a model's action ``space`` on an ``EpisodeStore`` (its ``state_names``, ``has_pose``);
    ``moves_by_name``: the benchmark's action name -> state name (``Locators.moves``)."""
    names = tuple(store.state_names)
    targets = set(getattr(space, "targets", ()))
    if space.kind == "delta_ee":
        if not store.has_pose:
            return Moved(how="delta_ee actions, and the store records no end-effector pose")
        return Moved("ee_pose", (0, 1, 2), (0, 1, 2), (0, 1, 2), ("x", "y", "z"), "delta_ee: the end-effector pose")
    pairs, how = [], ""
    measured = tuple(getattr(space, "measured", ()) or ())
    if measured and store.state_dim:
        pairs, how = [(i, j) for i, j in enumerate(measured) if 0 <= j < store.state_dim], \
            "the model's action space (measured)"
    elif moves_by_name and store.state_dim:
        pairs = [(space.names.index(a), names.index(s)) for a, s in moves_by_name.items()
                 if a in space.names and s in names]
        how = "the benchmark's declaration (Locators.moves)"
    elif store.state_dim == space.dim:
        pairs, how = [(i, i) for i in range(space.dim)], "the recorded state has the action's dimension"
    if not pairs:
        return Moved(how=f"{space.kind} actions: neither the action space (measured), the benchmark nor the state's "
                         "dimension says which recorded entry they move")
    axes, entries = tuple(i for i, _ in pairs), tuple(j for _, j in pairs)
    pose = tuple(j for i, j in pairs if i not in targets)
    return Moved("state", axes, entries, pose, tuple(names[j] for j in pose), how)


def gains(space) -> np.ndarray:
    """float [dim]: the measured quantity's units per action unit per second (``ActionSpace.gains`` where the space
    has one, else 1)."""
    g = getattr(space, "gains", None)
    return np.ones(space.dim) if g is None else np.asarray(g, np.float64)


def is_rate(space, axis: int) -> bool:
    """Whether ``axis`` integrates (velocity: per second; delta_ee xyz / rotation: per step) rather than being a
    target the robot is driven to (absolute actions, a gripper)."""
    if space.kind == "absolute":
        return False
    if space.kind == "delta_ee":
        return axis != 6
    return axis not in set(getattr(space, "targets", ()))


def shift_displacement(space, axis: int, delta: float, n: int, dt: float) -> float:
    """How far shifting ``axis`` of each of ``n`` model-rate actions by ``delta`` (raw units) displaces what it moves
    after them: velocity ``delta * gain * dt * n``, delta_ee ``delta * n`` (each step's delta adds), a target
    ``delta`` (the target itself moved)."""
    if not is_rate(space, axis):
        return float(delta)
    if space.kind == "delta_ee":
        return float(delta) * n
    return float(delta) * float(gains(space)[axis]) * dt * n


def chunk_displacement(space, actions: np.ndarray, dt: float) -> np.ndarray:
    """float [A]: what the model-rate ``actions`` [n, A] of one chunk command, per axis, in the units of
    :func:`shift_displacement` (rates summed; targets: the last minus the first)."""
    a = np.asarray(actions, np.float64)
    out = np.empty(a.shape[1])
    for i in range(a.shape[1]):
        out[i] = shift_displacement(space, i, a[:, i].sum() / len(a), len(a), dt) if is_rate(space, i) \
            else a[-1, i] - a[0, i]
    return out
