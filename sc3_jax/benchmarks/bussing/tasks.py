"""Objects, tasks, prompts and seeded initial conditions of the table-bussing benchmark.

Two tasks share one scene:
  * ``bussing`` (task id 0): utensil-class objects go to the utensil bin, trash-class objects to the trash can;
  * ``reverse`` (task id 1): the destinations are swapped. Reverse bussing never enters world-model training data.

An initial condition is a pure function of ``(seed, task)``. The object layout and container positions depend on the
seed only, so ``bussing`` and ``reverse`` with the same seed start from the same table; the prompt wording depends
on both.
"""
from __future__ import annotations

import dataclasses

import numpy as np

TASKS = ("bussing", "reverse")
SPLITS = {"bussing": "in_distribution", "reverse": "out_of_distribution"}  # task -> split, in-distribution first
CRITERIA = ("language", "lifting", "placing")  # per object, ordered and cumulative (``criteria.py``)
CONTAINERS = ("bin", "can")  # utensil bin, trash can
CLASSES = ("utensil", "trash")
# task id -> the one instruction per task that a prompted (openpi) policy is sent where an episode's own wording is not
# at hand (an .npz of initial conditions, `sc3 serve-policy --benchmark bussing`'s table): ``Benchmark.prompts``
PROMPTS = {0: "put the utensils in the bin and the trash in the trash can",  # bussing (in distribution)
           1: "put the utensils in the trash can and the trash in the bin"}  # reverse bussing (out of distribution)


@dataclasses.dataclass(frozen=True)
class ObjectSpec:
    name: str
    cls: str  # "utensil" or "trash"
    geom: str  # MuJoCo geom type
    size: tuple[float, ...]  # MuJoCo size of that geom type
    rgba: tuple[float, float, float, float]
    half_height: float  # resting half height above the table (centre z when standing)
    words: str  # how a prompt names it

    @property
    def class_id(self) -> int:
        return CLASSES.index(self.cls)


OBJECTS: tuple[ObjectSpec, ...] = (
    ObjectSpec("cup", "utensil", "cylinder", (0.028, 0.034), (0.90, 0.12, 0.12, 1), 0.034, "red cup"),
    ObjectSpec("bowl", "utensil", "cylinder", (0.036, 0.018), (1.00, 0.60, 0.05, 1), 0.018, "orange bowl"),
    ObjectSpec("spoon", "utensil", "box", (0.052, 0.015, 0.010), (0.98, 0.92, 0.15, 1), 0.010, "yellow spoon"),
    ObjectSpec("bag", "trash", "ellipsoid", (0.036, 0.030, 0.026), (0.15, 0.75, 0.20, 1), 0.026, "green bag"),
    ObjectSpec("bottle", "trash", "cylinder", (0.022, 0.044), (0.10, 0.30, 0.95, 1), 0.044, "blue bottle"),
    ObjectSpec("lid", "trash", "cylinder", (0.033, 0.008), (0.70, 0.15, 0.85, 1), 0.008, "purple lid"),
)
OBJECT_NAMES = tuple(o.name for o in OBJECTS)
OBJECT_BY_NAME = {o.name: o for o in OBJECTS}

# Workspace geometry (metres; the table surface is z = 0).
SPAWN_X = (-0.21, 0.03)  # keeps every object footprint clear of the containers
SPAWN_Y = (-0.19, 0.19)
MIN_SPACING = 0.095
BIN_XY = (0.20, -0.135)
CAN_XY = (0.20, 0.135)
CONTAINER_JITTER = 0.02


def task_id(task: str | int) -> int:
    if isinstance(task, (int, np.integer)):
        if int(task) not in (0, 1):
            raise ValueError(f"unknown task id {task}")
        return int(task)
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
    return TASKS.index(task)


def destination(obj_cls: str, task: str | int) -> str:
    """Container an object of class ``obj_cls`` must go to under ``task``."""
    home = "bin" if obj_cls == "utensil" else "can"
    if task_id(task) == 1:
        return "can" if home == "bin" else "bin"
    return home


# A template: opening, then one clause per non-empty object group, joined. Clause fields: {objs} the group's noun
# phrase ("the red cup and the yellow spoon"), {goes} the verb agreeing with it. Groups: "u" utensils, "t" trash.
# An empty group's clause is left out (no "nothing goes in the trash"); after an opening that ends a sentence the
# body starts with a capital.
_TEMPLATES: dict[int, tuple[tuple[str, tuple[tuple[str, str], ...], str], ...]] = {
    0: (("Bus the table: ", (("u", "put {objs} in the utensil bin"), ("t", "put {objs} in the trash can")), " and "),
        ("Clear the table. ", (("u", "{objs} {goes} in the bin"), ("t", "{objs} {goes} in the trash")), "; "),
        ("Tidy up: ", (("u", "{objs} into the bin"), ("t", "{objs} into the trash can")), ", ")),
    1: (("Reverse bussing: ", (("u", "put {objs} in the trash can"), ("t", "put {objs} in the utensil bin")),
         " and "),
        ("Do it the other way round: ", (("u", "{objs} into the trash can"), ("t", "{objs} into the utensil bin")),
         ", "),
        ("Swap the usual places: ",
         (("t", "{objs} {goes} in the utensil bin"), ("u", "{objs} {goes} in the trash can")), " and ")),
}
N_TEMPLATES = 3


def _join(words: list[str]) -> str:
    if len(words) == 1:
        return "the " + words[0]
    return "the " + ", the ".join(words[:-1]) + " and the " + words[-1]


def make_prompt(object_names: list[str], task: str | int, rng: np.random.Generator | None = None,
                template: int | None = None) -> str:
    """The instruction naming every object with its destination; ``template`` (0..2) or one drawn from ``rng``.
    Verbs agree with their subjects ("the spoon goes", "the cup and the bowl go")."""
    tid = task_id(task)
    if not object_names:
        raise ValueError("a prompt needs at least one object")
    if template is None:
        if rng is None:
            raise ValueError("give rng or template")
        template = int(rng.integers(N_TEMPLATES))
    opening, clauses, joiner = _TEMPLATES[tid][template]
    groups = {"u": [OBJECT_BY_NAME[n].words for n in object_names if OBJECT_BY_NAME[n].cls == "utensil"],
              "t": [OBJECT_BY_NAME[n].words for n in object_names if OBJECT_BY_NAME[n].cls == "trash"]}
    parts = []
    for g, fmt in clauses:
        if groups[g]:
            objs = _join(groups[g])
            parts.append(fmt.format(objs=objs, goes="goes" if len(groups[g]) == 1 else "go"))
    body = joiner.join(parts)
    if opening.rstrip().endswith("."):
        body = body[0].upper() + body[1:]
    return opening + body + "."


@dataclasses.dataclass(frozen=True)
class InitialCondition:
    seed: int
    task: str
    objects: tuple[str, ...]  # names of the objects on the table, in scene order
    object_xy: np.ndarray  # [n, 2]
    object_yaw: np.ndarray  # [n]
    bin_xy: np.ndarray  # [2]
    can_xy: np.ndarray  # [2]
    prompt: str

    def destinations(self) -> dict[str, str]:
        return {n: destination(OBJECT_BY_NAME[n].cls, self.task) for n in self.objects}

    def to_json(self) -> dict:
        return {"seed": self.seed, "task": self.task, "objects": list(self.objects),
                "object_xy": np.round(self.object_xy, 5).tolist(), "object_yaw": np.round(self.object_yaw, 5).tolist(),
                "bin_xy": np.round(self.bin_xy, 5).tolist(), "can_xy": np.round(self.can_xy, 5).tolist(),
                "prompt": self.prompt, "destinations": self.destinations()}


def make_initial_condition(seed: int, task: str | int = "bussing", n_objects: int = 3) -> InitialCondition:
    """Seeded, reproducible initial condition. Layout depends on ``seed`` only; the prompt on (seed, task)."""
    if not 1 <= n_objects <= len(OBJECTS):
        raise ValueError(f"n_objects must be in [1, {len(OBJECTS)}], got {n_objects}")
    tname = TASKS[task_id(task)]
    rng = np.random.default_rng([int(seed), 7919])
    names = [OBJECT_NAMES[i] for i in sorted(rng.choice(len(OBJECTS), size=n_objects, replace=False))]
    xy = np.zeros((n_objects, 2))
    for i in range(n_objects):
        for _ in range(1000):
            p = np.array([rng.uniform(*SPAWN_X), rng.uniform(*SPAWN_Y)])
            if i == 0 or np.min(np.linalg.norm(xy[:i] - p, axis=1)) >= MIN_SPACING:
                break
        xy[i] = p
    yaw = rng.uniform(-np.pi, np.pi, size=n_objects)
    bin_xy = np.asarray(BIN_XY) + rng.uniform(-CONTAINER_JITTER, CONTAINER_JITTER, size=2)
    can_xy = np.asarray(CAN_XY) + rng.uniform(-CONTAINER_JITTER, CONTAINER_JITTER, size=2)
    prompt = make_prompt(names, tname, np.random.default_rng([int(seed), 31, task_id(tname)]))
    return InitialCondition(int(seed), tname, tuple(names), xy, yaw, bin_xy, can_xy, prompt)
