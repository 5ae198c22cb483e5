"""The simulated benchmark's scorers (the protocol, ``RolloutView`` and the outcome form are the evaluation core's:
``evaluation/scorers.py``).

One interface, three kinds, interchangeable in a sweep of the simulated benchmark:

* :class:`SimScorer` -- the simulator's physics ground truth (real rollouts only; ``benchmarks/bussing/criteria.py``).
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

import numpy as np

from sc3_jax.benchmarks.bussing import perception
from sc3_jax.measures.metrics import outcome_category
from sc3_jax.evaluation.scorers import RolloutView, first_run, held

from .tasks import CRITERIA


def outcome(name: str, destination: str, language: bool, lifting: bool, placing: bool) -> dict:
    """One object's outcome as the benchmark's scorers give it: its criteria in their order, and its category."""
    passed = {"language": bool(language), "lifting": bool(lifting), "placing": bool(placing)}
    return {"object": name, "destination": destination, **passed, "outcome": outcome_category(passed)}


class SimScorer:
    name = "sim"

    def score(self, rollout: RolloutView) -> list[dict]:
        if rollout.physics is None:
            raise ValueError(f"{rollout.id}: simulator ground truth exists only for real (simulated) rollouts")
        return [outcome(o["name"], o["destination"], o["language"], o["lifting"], o["placing"])
                for o in rollout.physics]


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
        from sc3_jax.evaluation import degrade
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
