"""Ground-truth success criteria from physics state, per object handled.

Ordered criteria (the outcome category is the first one violated, else "no failure"):
  1. ``language``: the object was never brought into the *wrong* container (the object handled and its destination
     match the instruction). An object that is never touched does not violate it (it fails lifting instead).
  2. ``lifting``: the object's bottom was lifted at least ``LIFT_CLEARANCE`` above the table at some step.
  3. ``placing``: at the end the object rests inside the instructed container (inside the inner footprint, below the
     rim, not held, speed below ``REST_SPEED``).

Everything here is a pure function of arrays, so it can be tested on hand-built states.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .scene import CONTAINER_GEOM
from .tasks import CRITERIA, OBJECT_BY_NAME, InitialCondition

OUTCOMES = ("language", "lifting", "placing", "no failure")
LIFT_CLEARANCE = 0.03
REST_SPEED = 0.25
RIM_MARGIN = 0.06  # objects stacked on another object inside a container still count as inside


def inside_container(pos: np.ndarray, container_xy: np.ndarray, container: str) -> np.ndarray:
    """pos [..., 3] -> bool [...]: centre within the inner footprint and below the rim (+ ``RIM_MARGIN``, so that a
    stack of objects inside the container counts)."""
    inner, height = CONTAINER_GEOM[container]
    pos = np.asarray(pos)
    d = np.abs(pos[..., :2] - np.asarray(container_xy))
    return (d[..., 0] < inner) & (d[..., 1] < inner) & (pos[..., 2] < height + RIM_MARGIN) & (pos[..., 2] > -0.01)


@dataclasses.dataclass(frozen=True)
class ObjectOutcome:
    name: str
    destination: str
    language: bool
    lifting: bool
    placing: bool
    outcome: str
    final_container: str | None  # container it ends in (None = neither)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def outcome_category(language: bool, lifting: bool, placing: bool) -> str:
    if not language:
        return "language"
    if not lifting:
        return "lifting"
    if not placing:
        return "placing"
    return "no failure"


def evaluate_object(name: str, trajectory: np.ndarray, half_height: float, destination: str,
                    containers: dict[str, np.ndarray], final_speed: float = 0.0,
                    held_at_end: bool = False) -> ObjectOutcome:
    """trajectory: [T, 3] positions of the object's centre over the episode (including the final state)."""
    traj = np.asarray(trajectory, np.float64).reshape(-1, 3)
    wrong = [c for c in containers if c != destination]
    language = not any(bool(np.any(inside_container(traj, containers[c], c))) for c in wrong)
    # bottom above the table; inside a container the floor is higher, which only helps (it was lifted to get in)
    lifting = bool(np.max(traj[:, 2] - half_height) > LIFT_CLEARANCE)
    final = traj[-1]
    final_container = next((c for c in containers if bool(inside_container(final, containers[c], c))), None)
    placing = bool(final_container == destination and final_speed < REST_SPEED and not held_at_end)
    return ObjectOutcome(name, destination, language, lifting, placing,
                         outcome_category(language, lifting, placing), final_container)


def success_rates(outcomes: list[ObjectOutcome] | list[dict]) -> dict[str, float]:
    """Per-criterion success rate (each criterion on its own) and the outcome-category distribution."""
    rows = [o.to_json() if isinstance(o, ObjectOutcome) else o for o in outcomes]
    n = max(len(rows), 1)
    out = {c: float(sum(bool(r[c]) for r in rows) / n) for c in CRITERIA}
    out.update({f"outcome/{k}": float(sum(r["outcome"] == k for r in rows) / n) for k in OUTCOMES})
    out["n_objects"] = len(rows)
    return out



def evaluate_episode(ic: InitialCondition, trajectory: np.ndarray, final_speeds: np.ndarray | None = None,
                     held_at_end: str | None = None, containers: dict[str, np.ndarray] | None = None
                     ) -> list[ObjectOutcome]:
    """trajectory [T, n, 3] of the episode's objects (``ic.objects`` order) -> one outcome per object."""
    traj = np.asarray(trajectory)
    containers = containers or {"bin": np.asarray(ic.bin_xy), "can": np.asarray(ic.can_xy)}
    speeds = np.zeros(len(ic.objects)) if final_speeds is None else np.asarray(final_speeds)
    dest = ic.destinations()
    return [evaluate_object(n, traj[:, i], OBJECT_BY_NAME[n].half_height, dest[n], containers, float(speeds[i]),
                            held_at_end == n) for i, n in enumerate(ic.objects)]
