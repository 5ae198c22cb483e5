"""Scorers: a rollout -> one outcome per object (its benchmark's criteria as booleans, in order, + category; e.g. the
simulated benchmark's ``language``, ``lifting``, ``placing``), or, for
any robot, a rollout -> ``{criterion: bool}`` (the ``--scorer module:attr`` contract, at the end of this module).

The evaluation core's side: what a scorer sees (:class:`RolloutView`), the :class:`Scorer` protocol, runs of a
predicate (:func:`first_run`, :func:`held`), the agreement of two scorers, and any
robot's ``--scorer module:attr``. A benchmark brings its own scorers (the simulated benchmark's physics, perception
and human scorers: ``benchmarks/bussing/scorers.py``).
"""
from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np

from sc3_jax.core import module_attr
from sc3_jax.core.errors import UserError
from sc3_jax.measures.metrics import criteria_of


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


def agreement(scored: list[list[dict]], truth: list[list[dict]]) -> dict[str, float]:
    """Per criterion (each object's: ``metrics.criteria_of``) and for the outcome category, the fraction of objects
    on which two scorers agree."""
    pairs = [(a, b) for xs, ys in zip(scored, truth, strict=True) for a, b in zip(xs, ys, strict=True)]
    if not pairs:
        raise ValueError("agreement: no objects")
    return {k: float(np.mean([a[k] == b[k] for a, b in pairs])) for k in criteria_of(pairs[0][1]) + ("outcome",)} | \
        {"n_objects": len(pairs)}


# ================================================================================================================
# Any robot's scorer: ``--scorer module:attr`` (``sc3 sweep episodes --data``, docs/your_robot.md)
# ================================================================================================================
class OutcomeScorer(Protocol):
    """The contract of a ``--scorer module:attr``: called with one :class:`RolloutView` -- ``frames`` uint8 [V, T, H,
    W, 3] (the last initial context frame, then the imagined frames kept), ``state`` float32 [T, S] (the imagined
    robot state at those frames) or None, ``id`` (the initial condition's episode id), ``instruction`` (its prompt)
    -- it returns ``{criterion: bool}``, e.g. ``{"success": True}``, with the same criteria for every rollout."""

    def __call__(self, rollout: RolloutView) -> Mapping[str, bool]: ...


DETECTOR_PREFIX = "detector:"  # --scorer detector:DIR


def load_outcome_scorer(spec: str) -> Callable[[RolloutView], dict[str, bool]]:
    """The scorer ``spec`` = ``package.module:attr`` names: a function (called with each view), a class (built with
    no arguments; then its ``score`` method, else the instance, is called) or an object with a ``score`` method or
    ``__call__``; or ``detector:DIR``, a success detector ``sc3 train-detector`` trained on the lab's labelled
    episodes (``success_detector.py``). One-line UserError naming ``spec`` when it cannot be imported or called."""
    if spec.startswith(DETECTOR_PREFIX):
        from sc3_jax.evaluation import success_detector
        return success_detector.load(spec[len(DETECTOR_PREFIX):])
    if ":" not in spec:  # the one thing a scorer must return, said where the spelling is wrong
        raise UserError(f"--scorer {spec!r}: expected package.module:attr (a function or class taking a RolloutView "
                        "and returning {criterion: bool})")
    obj = module_attr.load(spec, "--scorer")
    if inspect.isclass(obj):
        try:
            obj = obj()
        except TypeError as e:
            raise UserError(f"--scorer {spec!r}: the class must build with no arguments ({e})") from None
    fn = getattr(obj, "score", None) if not inspect.isfunction(obj) else None
    fn = fn if callable(fn) else obj
    if not callable(fn):
        raise UserError(f"--scorer {spec!r}: {type(obj).__name__} is neither callable nor has a score method")
    try:  # it is called with one RolloutView: a function taking none (os:getcwd) is said now, not after the rollouts
        inspect.signature(fn).bind(None)
    except TypeError:
        raise UserError(f"--scorer {spec!r}: takes {inspect.signature(fn)}, not one RolloutView; give a function "
                        "or class taking a RolloutView and returning {criterion: bool}") from None
    except ValueError:  # no signature to read (some builtins): its first call says
        pass
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
