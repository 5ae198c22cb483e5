"""Faithfulness metrics: how well success rates measured inside the world model ("evaluator") track the real
(simulated-physics) success rates, plus the per-rollout scores those rates are built from.

Definitions follow SIMPLER (Li et al. 2024, "Evaluating Real-World Robot Manipulation Policies in Simulation"):

* Each ``(policy, criterion)`` pair is one point; ``S`` are the evaluator's success rates, ``R`` the real ones.
* Pearson r = sum(x*y) / sqrt(sum(x^2) * sum(y^2)) with x = S - mean(S), y = R - mean(R).
* MMRV = (1/N) * sum_i max_j |R_i - R_j| * 1[(S_i > S_j) != (R_i > R_j)]   (empty max = 0, strict ``>``).

Both formulas live in ``sc3_jax/stats/`` (one definition for a point and for a batch of bootstrap draws); here they
take checked per-split vectors.

Criteria per object are a benchmark's, ordered and cumulative (e.g. the simulated benchmark's: following the
instruction -> lifting -> placing). An object passes criterion ``c`` only if it passes ``c`` *and every criterion
before it* (an object that was never lifted has not been placed, whatever a scorer says about placing). The outcome
category of an object is its first violated criterion, or ``"no_failure"``. An outcome carries its own criteria:
its boolean entries, in their order (:func:`criteria_of`; a results store writes them sorted, so its sweep records
their order: ``results.criteria_order``); a per-object record, every field beyond its case's.

Everything here is plain numpy / Python: metrics run on a handful of numbers, never inside a jitted graph.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from sc3_jax.stats import correlation, rank_violation

NO_FAILURE = "no_failure"
OVERALL = "overall"

# The fields that name a per-object record's case (a Mapping with these keys, or an object with these attributes);
# its criteria follow them
CASE_FIELDS: tuple[str, ...] = ("policy", "split", "episode", "object")


def criteria_of(outcome: Mapping[str, Any]) -> tuple[str, ...]:
    """The criteria of one object's outcome (a scorer's ``{criterion: bool, ...}``), in their order: its boolean
    entries (the rest name the object, its destination, its category)."""
    return tuple(k for k, v in outcome.items() if isinstance(v, (bool, np.bool_)))


def categories(criteria: Sequence[str]) -> tuple[str, ...]:
    """The outcome categories of ``criteria``: each criterion (the first one violated), then ``"no_failure"``."""
    return (*criteria, NO_FAILURE)


# --------------------------------------------------------------------------------------------------------------
# Pearson and MMRV
# --------------------------------------------------------------------------------------------------------------

def _paired_vectors(evaluator: Any, real: Any) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for name, values in (("evaluator", evaluator), ("real", real)):
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name}: expected a 1-D sequence of numbers ({e})") from None
        if arr.ndim != 1:
            raise ValueError(f"{name}: expected a 1-D sequence of success rates, got shape {list(arr.shape)}")
        out.append(arr)
    s, r = out
    if s.shape[0] != r.shape[0]:
        raise ValueError(f"evaluator and real must have the same length, got {s.shape[0]} and {r.shape[0]}")
    if s.shape[0] < 2:
        raise ValueError(f"need at least 2 paired points, got {s.shape[0]}")
    for name, arr in (("evaluator", s), ("real", r)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise ValueError(f"{name}: non-finite values at indices {bad.tolist()}")
    return s, r


def pearson(evaluator: Sequence[float] | np.ndarray, real: Sequence[float] | np.ndarray) -> float:
    """Pearson r between the evaluator's and the real success rates: ``stats.correlation.pearson`` (the formula,
    and ``nan`` for a constant vector, are documented there) on two checked vectors.

    Raises ValueError for different lengths, fewer than 2 points, non-finite or non-numeric values, or non-1-D
    input.
    """
    return float(correlation.pearson(*_paired_vectors(evaluator, real)))


def mmrv(evaluator: Sequence[float] | np.ndarray, real: Sequence[float] | np.ndarray) -> float:
    """Mean Maximum Rank Violation of the evaluator's ranking against the real one (lower is better, >= 0):
    ``stats.rank_violation.mmrv`` (the formula, and why it is not symmetric, are documented there) on two checked
    vectors.

    Raises ValueError for different lengths, fewer than 2 points, non-finite or non-numeric values, or non-1-D
    input.
    """
    return float(rank_violation.mmrv(*_paired_vectors(evaluator, real)))


# --------------------------------------------------------------------------------------------------------------
# Per-object criteria -> categories and success rates
# --------------------------------------------------------------------------------------------------------------

def _as_bool(value: Any, what: str) -> bool:
    """Accept bool / numpy bool / the integers 0 and 1; refuse anything else (e.g. the truthy string "False")."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and int(value) in (0, 1):
        return bool(int(value))
    raise ValueError(f"{what}: expected a boolean (True/False or 0/1), got {value!r}")


def _criteria_values(passed: Mapping[str, Any] | Sequence[Any], criteria: Sequence[str] | None = None,
                     what: str = "passed") -> tuple[tuple[str, ...], tuple[bool, ...]]:
    """(criteria, their values) of ``passed``: a mapping (its boolean entries when ``criteria`` is None) or a
    sequence of booleans in ``criteria`` order."""
    if isinstance(passed, Mapping):
        criteria = tuple(criteria_of(passed) if criteria is None else criteria)
        missing = [c for c in criteria if c not in passed]
        if missing or not criteria:
            raise ValueError(f"{what}: missing criteria {missing or 'all'} (need {list(criteria) or 'some'})")
        return criteria, tuple(_as_bool(passed[c], f"{what}[{c!r}]") for c in criteria)
    if criteria is None:
        raise ValueError(f"{what}: a sequence of booleans needs its criteria named")
    criteria = tuple(criteria)
    if isinstance(passed, (str, bytes)):
        raise ValueError(f"{what}: expected a mapping or a sequence of {len(criteria)} booleans, got {passed!r}")
    values = list(passed)
    if len(values) != len(criteria):
        raise ValueError(f"{what}: expected {len(criteria)} booleans {list(criteria)}, got {len(values)}")
    return criteria, tuple(_as_bool(v, f"{what}[{i}] ({criteria[i]})") for i, v in enumerate(values))


def cumulative_passes(passed: Mapping[str, Any] | Sequence[Any], criteria: Sequence[str] | None = None
                      ) -> dict[str, bool]:
    """Cumulative criteria: criterion c counts as passed only if c and every criterion before it passed.

    ``passed`` is an outcome (its boolean entries are its criteria, in order; or those of ``criteria``), or a
    sequence of booleans in ``criteria`` order. E.g. (language=False, lifting=True, placing=True) -> all three False.
    """
    out: dict[str, bool] = {}
    ok = True
    for c, v in zip(*_criteria_values(passed, criteria)):
        ok = ok and v
        out[c] = ok
    return out


def outcome_category(passed: Mapping[str, Any] | Sequence[Any], criteria: Sequence[str] | None = None) -> str:
    """The first violated criterion in the criteria's order, else "no_failure".

    Criteria after the first failure are ignored (they count as failed, see ``cumulative_passes``).
    """
    for c, v in zip(*_criteria_values(passed, criteria)):
        if not v:
            return c
    return NO_FAILURE


def _field(record: Any, name: str, index: int) -> Any:
    if isinstance(record, Mapping):
        if name not in record:
            raise ValueError(f"record {index}: missing field {name!r}")
        return record[name]
    if not hasattr(record, name):
        raise ValueError(f"record {index}: missing field {name!r}")
    return getattr(record, name)


def record_criteria(record: Any) -> tuple[str, ...]:
    """The criteria of a per-object record (a mapping or a dataclass): its fields beyond the case's
    (``CASE_FIELDS``), in their order."""
    if isinstance(record, Mapping):
        names = list(record)
    elif dataclasses.is_dataclass(record):
        names = [f.name for f in dataclasses.fields(record)]
    else:
        raise ValueError(f"a {type(record).__name__} record: name its criteria (criteria=...)")
    return tuple(k for k in names if k not in CASE_FIELDS)


def _parse_records(records: Iterable[Any], criteria: Sequence[str] | None = None
                   ) -> tuple[tuple[str, ...], list[tuple[tuple[Hashable, ...], tuple[bool, ...]]]]:
    """(criteria, [(case key (policy, split, episode, object), criteria bools)]), refusing duplicate cases; the
    criteria are ``criteria``, else the first record's (:func:`record_criteria`)."""
    parsed = []
    seen: dict[tuple[Hashable, ...], int] = {}
    for i, rec in enumerate(records):
        if criteria is None:
            criteria = record_criteria(rec)
        key = tuple(_field(rec, f, i) for f in CASE_FIELDS)
        if key in seen:
            raise ValueError(f"record {i}: duplicate case (policy, split, episode, object) = {key!r} "
                             f"(first seen at record {seen[key]})")
        seen[key] = i
        _, values = _criteria_values({c: _field(rec, c, i) for c in criteria}, criteria, what=f"record {i}")
        parsed.append((key, values))
    return tuple(criteria or ()), parsed


def success_rates(records: Iterable[Any], criteria: Sequence[str] | None = None) -> dict[tuple[Hashable, str], float]:
    """Success rate per (policy, criterion): the mean over all objects and episodes of the *cumulative* pass.

    Each record is one object in one episode: a Mapping (or an object with attributes) with fields
    ``policy, split, episode, object`` and then its criteria (``criteria``, else the first record's further fields;
    booleans or 0/1), e.g. ``language, lifting, placing``. An object passes criterion c only if it passes c and
    every criterion before it (see ``cumulative_passes``), so for every policy rate(language) >= rate(lifting) >=
    rate(placing).

    All records given are pooled (use ``success_rates_by_split`` for per-split rates). Returns a dict with keys
    ``(policy, criterion)`` for every policy present and every criterion. Raises ValueError for an
    empty input, a missing field, a non-boolean criterion or a duplicate (policy, split, episode, object) case.
    """
    criteria, parsed = _parse_records(records, criteria)
    if not parsed:
        raise ValueError("success_rates: no records")
    passes: dict[Hashable, list[tuple[bool, ...]]] = {}
    for key, values in parsed:
        cum = tuple(all(values[: k + 1]) for k in range(len(criteria)))
        passes.setdefault(key[0], []).append(cum)
    out: dict[tuple[Hashable, str], float] = {}
    for policy, rows in passes.items():
        arr = np.asarray(rows, dtype=np.float64)
        for k, c in enumerate(criteria):
            out[(policy, c)] = float(arr[:, k].mean())
    return out


def group_by_split(records: Iterable[Any]) -> dict[Hashable, list[Any]]:
    """Records grouped by their ``split`` field, in first-seen order."""
    groups: dict[Hashable, list[Any]] = {}
    for i, rec in enumerate(records):
        groups.setdefault(_field(rec, "split", i), []).append(rec)
    return groups


def success_rates_by_split(records: Iterable[Any], criteria: Sequence[str] | None = None
                           ) -> dict[Hashable, dict[tuple[Hashable, str], float]]:
    """``{split: success_rates(records of that split)}`` — the input ``faithfulness`` expects."""
    return {split: success_rates(recs, criteria) for split, recs in group_by_split(records).items()}


def outcome_categories(records: Iterable[Any], criteria: Sequence[str] | None = None
                       ) -> dict[tuple[Hashable, ...], str]:
    """``{(policy, split, episode, object): outcome category}`` for per-object records (see ``success_rates``)."""
    criteria, parsed = _parse_records(records, criteria)
    return {key: outcome_category(values, criteria) for key, values in parsed}


# --------------------------------------------------------------------------------------------------------------
# Faithfulness table
# --------------------------------------------------------------------------------------------------------------

def faithfulness(evaluator_rates: Mapping[Hashable, Mapping[Hashable, float]],
                 real_rates: Mapping[Hashable, Mapping[Hashable, float]],
                 splits: Sequence[Hashable] | None = None) -> dict[Hashable, dict[str, float]]:
    """Pearson r and MMRV per split and overall.

    ``evaluator_rates`` and ``real_rates`` are ``{split: {(policy, criterion): success rate}}`` (as returned by
    ``success_rates_by_split``). ``splits`` selects and orders the splits to score (default: the evaluator's
    splits, in its order). Within a split, the (policy, criterion) keys of evaluator and real must be identical —
    a missing point would silently change both metrics, so a mismatch raises ValueError naming the keys.

    "overall" scores the concatenation of every selected split's points, one point per
    (split, policy, criterion): it rewards an evaluator that also gets the in- vs out-of-distribution difficulty
    right (it is not the metric of rates pooled over splits).

    Returns ``{split: {"pearson": r, "mmrv": m, "n": points}, ..., "overall": {...}}``; r is nan for a constant
    vector (see ``pearson``). Raises ValueError for a split absent from either side, a split named "overall",
    or a split with fewer than 2 points.
    """
    if splits is None:
        splits = list(evaluator_rates)
    splits = list(splits)
    if not splits:
        raise ValueError("faithfulness: no splits")
    if len(set(splits)) != len(splits):
        raise ValueError(f"faithfulness: repeated splits in {splits}")
    out: dict[Hashable, dict[str, float]] = {}
    all_s: list[float] = []
    all_r: list[float] = []
    for split in splits:
        if split == OVERALL:
            raise ValueError(f"a split may not be named {OVERALL!r} (reserved for the pooled result)")
        for name, rates in (("evaluator_rates", evaluator_rates), ("real_rates", real_rates)):
            if split not in rates:
                raise ValueError(f"{name}: no split {split!r} (have {list(rates)})")
        ev, re = evaluator_rates[split], real_rates[split]
        only_ev = [k for k in ev if k not in re]
        only_re = [k for k in re if k not in ev]
        if only_ev or only_re:
            raise ValueError(f"split {split!r}: (policy, criterion) keys differ; only in evaluator: {only_ev}; "
                             f"only in real: {only_re}")
        keys = list(ev)
        s = [ev[k] for k in keys]
        r = [re[k] for k in keys]
        try:
            out[split] = {"pearson": pearson(s, r), "mmrv": mmrv(s, r), "n": len(keys)}
        except ValueError as e:
            raise ValueError(f"split {split!r}: {e}") from None
        all_s.extend(s)
        all_r.extend(r)
    out[OVERALL] = {"pearson": pearson(all_s, all_r), "mmrv": mmrv(all_s, all_r), "n": len(all_s)}
    return out


# --------------------------------------------------------------------------------------------------------------
# Failure-mode reproduction
# --------------------------------------------------------------------------------------------------------------

def _check_categories(cats: Mapping[Hashable, str], known: Sequence[str], name: str) -> None:
    for key, cat in cats.items():
        if cat not in known:
            raise ValueError(f"{name}[{key!r}]: unknown category {cat!r} (expected one of {list(known)})")


def reproduction_counts(real_categories: Mapping[Hashable, str],
                        evaluator_categories: Mapping[Hashable, str],
                        criteria: Sequence[str]) -> dict[str, tuple[int, int]]:
    """``{real category: (cases the evaluator reproduced, cases with that real category)}``.

    Both arguments map a case id (e.g. ``(policy, split, episode, object)`` from ``outcome_categories``) to an
    outcome category of ``criteria`` (:func:`categories`); their case ids must be identical (ValueError otherwise).
    Only categories that occur in ``real_categories`` appear, in the categories' order.
    """
    known = categories(criteria)
    _check_categories(real_categories, known, "real_categories")
    _check_categories(evaluator_categories, known, "evaluator_categories")
    only_re = [k for k in real_categories if k not in evaluator_categories]
    only_ev = [k for k in evaluator_categories if k not in real_categories]
    if only_re or only_ev:
        raise ValueError(f"case ids differ; only in real: {only_re}; only in evaluator: {only_ev}")
    if not real_categories:
        raise ValueError("reproduction_counts: no cases")
    counts = {c: [0, 0] for c in known}
    for key, cat in real_categories.items():
        counts[cat][1] += 1
        counts[cat][0] += int(evaluator_categories[key] == cat)
    return {c: (m, n) for c, (m, n) in counts.items() if n > 0}


def reproduction_rate(real_categories: Mapping[Hashable, str],
                      evaluator_categories: Mapping[Hashable, str], criteria: Sequence[str]) -> dict[str, float]:
    """Per real outcome category, the fraction of its cases whose evaluator category is the same.

    E.g. ``rate["lifting"]`` = (# cases that really failed at lifting and that the evaluator also scored as a
    lifting failure) / (# cases that really failed at lifting). Categories with no real case are *absent* from
    the result (the rate is undefined; a KeyError is louder than a nan). Same inputs and errors as
    ``reproduction_counts``.
    """
    return {c: m / n for c, (m, n) in reproduction_counts(real_categories, evaluator_categories, criteria).items()}


# --------------------------------------------------------------------------------------------------------------
# Frame fidelity and episode termination
# --------------------------------------------------------------------------------------------------------------

def psnr(pred: np.ndarray, target: np.ndarray, max_value: float = 255.0,
         axis: int | tuple[int, ...] = (-3, -2, -1)) -> np.ndarray | float:
    """Peak signal-to-noise ratio in dB: ``10 * log10(max_value^2 / mean((pred - target)^2))``.

    The mean runs over ``axis`` (default the last three: H, W, C), so ``[T, H, W, C]`` gives one value per frame
    and ``[V, T, H, W, C]`` one per view and frame. Works for uint8 (``max_value=255``) or float arrays (pass the
    range, e.g. ``max_value=1.0`` for [0, 1] frames). Differences are taken in float64, so uint8 inputs never wrap
    around. ``pred`` and ``target`` must have the same shape (no broadcasting).

    Identical frames (MSE = 0) give ``inf`` — no warning; averaging such values gives inf, so report a median or
    count them separately. Returns a float64 array of the remaining axes (a Python float when every axis is
    reduced). Raises ValueError for shape mismatch, non-finite values, a non-positive/non-finite ``max_value``, or
    integer inputs with values above ``max_value`` (a uint8 frame scored with ``max_value=1.0``).
    """
    p = np.asarray(pred)
    t = np.asarray(target)
    if p.shape != t.shape:
        raise ValueError(f"pred and target must have the same shape, got {list(p.shape)} and {list(t.shape)}")
    if not (math.isfinite(max_value) and max_value > 0):
        raise ValueError(f"max_value must be positive and finite, got {max_value}")
    for name, arr in (("pred", p), ("target", t)):
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
            raise ValueError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
        if np.issubdtype(arr.dtype, np.integer) and arr.size and int(arr.max()) > max_value:
            raise ValueError(f"{name}: integer values up to {int(arr.max())} exceed max_value={max_value}")
    pf = p.astype(np.float64)
    tf = t.astype(np.float64)
    if not (np.all(np.isfinite(pf)) and np.all(np.isfinite(tf))):
        raise ValueError("pred and target must be finite")
    value = psnr_from_mse(np.mean((pf - tf) ** 2, axis=axis), max_value)
    if np.ndim(value) == 0:
        return float(value)
    return value


def psnr_from_mse(mse, max_value: float = 255.0):
    """The PSNR formula (dB) of a mean squared error, elementwise; inf for 0. :func:`psnr` and the pooled /
    masked variants (``diagnose.psnr_from_sums``, ``tokenizer_train.psnr``) all end here."""
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(float(max_value) ** 2 / mse)


def psnr_by_view(pred: np.ndarray, target: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``pred`` / ``target`` [..., V, T, H, W, C] (an offline rollout's and the recorded ones), ``valid``
    bool [..., T] -> (:func:`psnr` per view and frame [..., V, T], its mean per view over the valid frames where
    finite [..., V]; nan for a view with none)."""
    p = np.asarray(psnr(pred, target))
    ok = np.asarray(valid, bool)[..., None, :] & np.isfinite(p)
    rows = [float(np.mean(x[m])) if m.any() else math.nan
            for x, m in zip(p.reshape(-1, p.shape[-1]), ok.reshape(-1, p.shape[-1]))]
    return p, np.asarray(rows, np.float64).reshape(p.shape[:-1])


def termination_rate(done_flags: Sequence[Any] | np.ndarray) -> float:
    """Fraction of episodes that terminated.

    ``done_flags`` is either one flag per episode (1-D) or per-step flags ``[episodes, steps]`` (2-D), where an
    episode counts as terminated if any of its steps is flagged. Flags must be bool or 0/1. Raises ValueError
    for no episodes, other dimensionality, or non-boolean values.
    """
    arr = np.asarray(done_flags)
    if arr.ndim not in (1, 2):
        raise ValueError(f"done_flags: expected 1-D [episodes] or 2-D [episodes, steps], got shape {list(arr.shape)}")
    if arr.shape[0] == 0:
        raise ValueError("done_flags: no episodes")
    if arr.dtype != np.bool_:
        if not np.issubdtype(arr.dtype, np.number) or not np.all((arr == 0) | (arr == 1)):
            raise ValueError("done_flags: expected booleans (True/False or 0/1)")
        arr = arr.astype(bool)
    per_episode = arr.any(axis=1) if arr.ndim == 2 else arr
    return float(per_episode.mean())
