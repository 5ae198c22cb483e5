"""Scorers: a rollout -> one outcome per object (``language``, ``lifting``, ``placing`` booleans + category), or, for
any robot, a rollout -> ``{criterion: bool}`` (the ``--scorer module:attr`` contract, at the end of this module).

One interface, three kinds, interchangeable in a sweep of the simulated benchmark:

* :class:`SimScorer` -- the simulator's physics ground truth (real rollouts only; ``sim/criteria.py``).
* :class:`PerceptionScorer` -- reads only frames: the learned per-object predicates of ``perception.py`` (lifted,
  in the bin, in the can), then the criteria's own logic. Works on real and imagined rollouts alike.
* :class:`HumanScorer` -- annotations imported from a blinded CSV (``annotation.py``).

Criteria from predicates, per object (a predicate "holds" when its probability is > 0.5 for ``min_run``
consecutive frames, 3 at the world model's 10 Hz = 0.3 s, so a misread frame or two do not decide an outcome; real
rollouts are scored at the same frame rate):
  lifting  = it was lifted for a run of ``min_run`` frames;
  nothing gets into a container without being lifted over its wall, so the container predicates count only from
  the first such lifted run on (an object next to the can, or one hidden by the arm, read as "in the can" before it
  was ever lifted is a misreading: on 312 real objects of the zoo (``perception_train --validate``) this rule
  raised lifting agreement from 0.974 to 0.994, language from 0.955 to 0.962, placing from 0.894 to 0.907);
  language = it never held in the *wrong* container;
  placing  = it is in the instructed container in every one of the last ``min_run`` frames (the settled tail: a
             real rollout ends once every object is at rest, an imagined one at its horizon), not in one frame.
The physics criteria also require the object to be at rest and released at the end; frames show that only
indirectly. The remaining disagreement is mostly the network's: objects at rest inside a container (occluded,
stacked) misread, measured by the sweep (``scorer_agreement``).
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np

from sc3_jax.errors import UserError
from sc3_jax.evaluate import perception
from sc3_jax.evaluate.metrics import CRITERIA, outcome_category


@dataclasses.dataclass
class RolloutView:
    """What a scorer may look at. ``physics``: the simulator's outcomes (real rollouts only). The benchmark's scorers
    read ``objects`` / ``destinations``; a ``--scorer module:attr`` of any robot reads ``frames``, ``state`` and
    ``instruction`` (``id``: the initial condition's episode id; never the policy's name: scoring is blind)."""
    id: str
    frames: np.ndarray  # uint8 [V, T, H, W, 3]
    objects: tuple[str, ...] = ()
    destinations: dict[str, str] = dataclasses.field(default_factory=dict)
    physics: list[dict] | None = None
    state: np.ndarray | None = None  # float32 [T, S] the (imagined) robot state at each frame, where there is one
    instruction: str = ""  # the episode's prompt


class Scorer(Protocol):
    name: str

    def score(self, rollout: RolloutView) -> list[dict]: ...  # one dict per object, in rollout.objects order


def outcome(name: str, destination: str, language: bool, lifting: bool, placing: bool) -> dict:
    passed = {"language": bool(language), "lifting": bool(lifting), "placing": bool(placing)}
    return {"object": name, "destination": destination, **passed, "outcome": outcome_category(passed)}


class SimScorer:
    name = "sim"

    def score(self, rollout: RolloutView) -> list[dict]:
        if rollout.physics is None:
            raise ValueError(f"{rollout.id}: simulator ground truth exists only for real (simulated) rollouts")
        return [outcome(o["name"], o["destination"], o["language"], o["lifting"], o["placing"])
                for o in rollout.physics]


def first_run(p: np.ndarray, min_run: int) -> int | None:
    """Start of the first run of ``min_run`` consecutive True steps of the bool series ``p`` [T] (None: no run)."""
    run = 0
    for i, v in enumerate(np.asarray(p, bool)):
        run = run + 1 if v else 0
        if run >= min_run:
            return i - min_run + 1
    return None


def held(p: np.ndarray, min_run: int) -> bool:
    """Whether the bool series ``p`` [T] is True for ``min_run`` consecutive steps somewhere."""
    return first_run(p, min_run) is not None


def criteria_from_predicates(probs: np.ndarray, objects, destinations: dict, min_run: int = 3) -> list[dict]:
    """probs [T, 6, 3] (perception.TYPES x PREDICATES) -> one outcome per object (see the module docstring)."""
    on = np.asarray(probs) > 0.5
    out = []
    for name in objects:
        k = perception.TYPES.index(name)
        lifted, in_bin, in_can = on[:, k, 0], on[:, k, 1], on[:, k, 2]
        first = first_run(lifted, min_run)
        after = np.arange(len(lifted)) >= (len(lifted) if first is None else first)  # containers count from here
        dest = destinations[name]
        right, wrong = (in_bin & after, in_can & after) if dest == "bin" else (in_can & after, in_bin & after)
        language = not held(wrong, min_run)
        lifting = first is not None
        placing = bool(len(right) and right[-min_run:].all())
        out.append(outcome(name, dest, language, lifting, placing))
    return out


class PerceptionScorer:
    name = "perception"

    def __init__(self, params: dict | None = None, min_run: int = 3):
        self.params = perception.load() if params is None else params
        self.min_run = min_run

    def predicates(self, frames: np.ndarray) -> np.ndarray:
        return perception.predict(self.params, frames)[0]

    def score(self, rollout: RolloutView) -> list[dict]:
        return criteria_from_predicates(self.predicates(rollout.frames), rollout.objects, rollout.destinations,
                                        self.min_run)

    def score_real(self, view: RolloutView, seed: int, stride: int, degradations: bool = True):
        """A real rollout as every sweep reads it: ``view.frames`` [V, T, ...] at the simulator's rate, read at
        every ``stride``-th frame and the last (the world model's frame rate, so real and imagined rollouts are read
        alike); with ``degradations`` also on the seeded degraded copies (``degrade.py``). Returns (outcomes,
        {kind: outcomes})."""
        from sc3_jax.evaluate import degrade
        scored = np.concatenate([view.frames[:, :-1:stride], view.frames[:, -1:]], 1)
        clean = dataclasses.replace(view, frames=scored)
        kinds = degrade.all_kinds(scored, seed) if degradations else {}
        return self.score(clean), {k: self.score(dataclasses.replace(view, frames=f)) for k, f in kinds.items()}

    def score_cuts(self, frames: np.ndarray, objects, destinations, frames_per_chunk: int, num_chunks: int,
                   prefix: int = 0) -> list[list[dict]]:
        """Outcomes of the rollout cut after each number of chunks: entry c scores ``prefix`` initial frames plus
        the first c chunks (entry ``num_chunks`` = the whole rollout). One perception pass serves every cut, so a
        tau sweep costs nothing extra (termination at chunk c keeps exactly the frames of chunks < c)."""
        probs = self.predicates(frames)
        return [criteria_from_predicates(probs[:prefix + c * frames_per_chunk], objects, destinations, self.min_run)
                for c in range(num_chunks + 1)]


class HumanScorer:
    """Outcomes from imported annotations: ``{(rollout id, object): {criterion: bool}}`` (``annotation.py``)."""
    name = "human"

    def __init__(self, labels: dict):
        self.labels = labels

    def score(self, rollout: RolloutView) -> list[dict]:
        out = []
        for name in rollout.objects:
            key = (rollout.id, name)
            if key not in self.labels:
                raise KeyError(f"no annotation for rollout {rollout.id!r}, object {name!r}")
            out.append(outcome(name, rollout.destinations[name], *(self.labels[key][c] for c in CRITERIA)))
        return out


def agreement(scored: list[list[dict]], truth: list[list[dict]]) -> dict[str, float]:
    """Per criterion (and for the outcome category), the fraction of objects on which two scorers agree."""
    pairs = [(a, b) for xs, ys in zip(scored, truth, strict=True) for a, b in zip(xs, ys, strict=True)]
    if not pairs:
        raise ValueError("agreement: no objects")
    return {k: float(np.mean([a[k] == b[k] for a, b in pairs])) for k in CRITERIA + ("outcome",)} | \
        {"n_objects": len(pairs)}


# ================================================================================================================
# Any robot's scorer: ``--scorer module:attr`` (``sc3 sweep --initial-conditions``, docs/your_robot.md)
# ================================================================================================================
class OutcomeScorer(Protocol):
    """The contract of a ``--scorer module:attr``: called with one :class:`RolloutView` -- ``frames`` uint8 [V, T, H,
    W, 3] (the last initial context frame, then the imagined frames kept), ``state`` float32 [T, S] (the imagined
    robot state at those frames) or None, ``id`` (the initial condition's episode id), ``instruction`` (its prompt)
    -- it returns ``{criterion: bool}``, e.g. ``{"success": True}``, with the same criteria for every rollout."""

    def __call__(self, rollout: RolloutView) -> Mapping[str, bool]: ...


def load_outcome_scorer(spec: str) -> Callable[[RolloutView], dict[str, bool]]:
    """The scorer ``spec`` = ``package.module:attr`` names: a function (called with each view), a class (built with
    no arguments; then its ``score`` method, else the instance, is called) or an object with a ``score`` method or
    ``__call__``. One-line UserError naming ``spec`` when it cannot be imported or called."""
    mod_name, colon, attr = spec.partition(":")
    if not colon or not mod_name or not attr:
        raise UserError(f"--scorer {spec!r}: expected package.module:attr (a function or class taking a RolloutView "
                        "and returning {criterion: bool})")
    try:
        obj = importlib.import_module(mod_name)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except ImportError as e:
        raise UserError(f"--scorer {spec!r}: cannot import {mod_name!r} ({e}); is it on PYTHONPATH?") from None
    except AttributeError:
        raise UserError(f"--scorer {spec!r}: {mod_name!r} has no attribute {attr!r}") from None
    if inspect.isclass(obj):
        try:
            obj = obj()
        except TypeError as e:
            raise UserError(f"--scorer {spec!r}: the class must build with no arguments ({e})") from None
    fn = getattr(obj, "score", None) if not inspect.isfunction(obj) else None
    fn = fn if callable(fn) else obj
    if not callable(fn):
        raise UserError(f"--scorer {spec!r}: {type(obj).__name__} is neither callable nor has a score method")
    return fn


def check_outcomes(spec: str, got, rollout_id: str, criteria: tuple[str, ...] | None = None) -> dict[str, bool]:
    """A scorer's answer as ``{criterion: bool}``, or a one-line UserError naming ``spec`` and the rollout: not a
    mapping, empty, a non-string key, a value that is not a boolean (``numpy.bool_`` is one; 0.7 or "yes" are not),
    or criteria other than ``criteria`` (those of the rollouts scored before: every rollout answers the same ones)."""
    where = f"--scorer {spec!r} on {rollout_id}"
    if not isinstance(got, Mapping) or not got:
        raise UserError(f"{where}: returned {type(got).__name__} {str(got)[:60]!r}, expected a non-empty dict "
                        "{criterion: bool}, e.g. {'success': True}")
    out = {}
    for k, v in got.items():
        if not isinstance(k, str) or not isinstance(v, (bool, np.bool_)):
            raise UserError(f"{where}: entry {k!r}: {type(v).__name__} {str(v)[:30]!r}; expected a string criterion "
                            "and a bool")
        out[k] = bool(v)
    if criteria is not None and tuple(sorted(out)) != tuple(criteria):
        raise UserError(f"{where}: criteria {sorted(out)}, the rollouts before answered {list(criteria)}; return "
                        "the same criteria for every rollout")
    return out
