"""sc3_jax.stats: each statistic's definition on a vector pair and on a batch of draws (one definition, so the same
numbers row by row), the degenerate cases, MMRV's cases from SIMPLER's definition, the seeded resampler and the
split-half halves, and the package's floor (numpy only, no other sc3_jax import)."""
import ast
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.stats import correlation, floor, interval, rank_violation, resample, split_half

# success rates k / m: what the statistics see (well conditioned, ties likely)
rates = st.integers(2, 24).flatmap(lambda k: st.tuples(
    st.lists(st.integers(0, 12), min_size=k, max_size=k), st.lists(st.integers(0, 12), min_size=k, max_size=k),
    st.integers(1, 12)))


def _pair(x):
    s, r, m = x
    return np.asarray(s, float) / m, np.asarray(r, float) / m


# -- Pearson -------------------------------------------------------------------------------------------------------
@given(rates)
@settings(max_examples=200, deadline=None)
def test_pearson_of_a_pair_is_numpys_corrcoef(x):
    s, r = _pair(x)
    v = correlation.pearson(s, r)
    if np.all(s == s[0]) or np.all(r == r[0]):
        assert math.isnan(v)
    else:
        assert v == pytest.approx(np.corrcoef(s, r)[0, 1], abs=1e-12)
        assert -1.0 <= v <= 1.0 and v == correlation.pearson(r, s)  # clipped; symmetric


@given(st.lists(rates, min_size=1, max_size=6), st.integers(2, 12))
@settings(max_examples=100, deadline=None)
def test_pearson_of_a_batch_is_the_pair_definition_row_by_row_bit_for_bit(xs, k):
    pairs = [_pair(x) for x in xs]
    s = np.array([np.resize(a, k) for a, _ in pairs])
    r = np.array([np.resize(b, k) for _, b in pairs])
    batch = correlation.pearson(s, r)
    assert batch.shape == (len(pairs),)
    np.testing.assert_array_equal(batch, [correlation.pearson(a, b) for a, b in zip(s, r)])  # nan == nan here
    np.testing.assert_array_equal(correlation.pearson(s[None], r[None])[0], batch)  # any leading shape


def test_pearson_of_a_constant_vector_is_nan_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(correlation.pearson([0.5, 0.5, 0.5], [0.1, 0.4, 0.9]))  # a blind evaluator
        assert math.isnan(correlation.pearson([0.1, 0.4, 0.9], [0.3, 0.3, 0.3]))  # constant real rates
        assert math.isnan(correlation.pearson([0.3, 0.3], [0.3, 0.3]))  # both
        assert math.isnan(correlation.pearson([0.1] * 7, np.arange(7) / 10))  # mean(0.1 x 7) != 0.1 in floats
        draws = correlation.pearson([[0.2, 0.2, 0.2], [0.1, 0.5, 0.9], [0.1, np.nan, 0.9]], [[0.1, 0.4, 0.9]] * 3)
    assert np.isnan(draws[0]) and draws[1] == pytest.approx(np.corrcoef([0.1, 0.5, 0.9], [0.1, 0.4, 0.9])[0, 1])
    assert np.isnan(draws[2])  # a draw with a missing rate is left out, not a number


def test_pearson_hand_case():
    assert correlation.pearson([1.0, 2.0, 3.0], [1.0, 3.0, 2.0]) == pytest.approx(0.5, abs=1e-15)
    assert correlation.pearson([1, 2, 3], [3, 2, 1]) == -1.0


# -- MMRV ------------------------------------------------------------------------------------------------------------
def _mmrv_loops(s, r):
    """REFERENCE.md's formula, literally: (1/N) sum_i max_j |R_i - R_j| 1[(S_i > S_j) != (R_i > R_j)]."""
    n = len(s)
    return sum(max(abs(r[i] - r[j]) * ((s[i] > s[j]) != (r[i] > r[j])) for j in range(n)) for i in range(n)) / n


@pytest.mark.parametrize("s,r,want", [
    ([0.1, 0.5, 0.9], [0.2, 0.3, 0.8], 0.0),  # a perfect ranking
    ([0.2, 0.1, 0.8], [0.3, 0.5, 0.9], 0.4 / 3),  # one swap, sized by the real gap (0.2 on each of two points)
    ([0.9, 0.1, 0.2], [0.1, 0.5, 0.7], 1.6 / 3),  # the max over j, not the sum
    ([0.5, 0.5, 0.9], [0.2, 0.6, 0.9], 0.4 / 3),  # evaluator tie over a real gap: a violation (strict >)
    ([0.2, 0.6, 0.9], [0.5, 0.5, 0.9], 0.0),  # real tie: costs nothing
    ([0.5, 0.5, 0.5], [0.1, 0.4, 0.9], 1.1 / 3),  # constant evaluator: mean(real - min(real))
    ([0.1, 0.4, 0.9], [0.5, 0.5, 0.5], 0.0),  # constant real
    ([0.5, 0.5], [0.2, 0.8], 0.3),  # argument order matters ...
    ([0.2, 0.8], [0.5, 0.5], 0.0),  # ... the size comes from the real side
])
def test_mmrv_cases_of_the_definition(s, r, want):
    assert rank_violation.mmrv(s, r) == pytest.approx(want, abs=1e-12)
    assert rank_violation.mmrv(s, r) == pytest.approx(_mmrv_loops(s, r), abs=1e-12)


@given(st.lists(rates, min_size=1, max_size=5), st.integers(2, 10))
@settings(max_examples=100, deadline=None)
def test_mmrv_batch_is_the_pair_definition_row_by_row(xs, k):
    pairs = [_pair(x) for x in xs]
    s = np.array([np.resize(a, k) for a, _ in pairs])
    r = np.array([np.resize(b, k) for _, b in pairs])
    batch = rank_violation.mmrv(s, r)
    np.testing.assert_array_equal(batch, [rank_violation.mmrv(a, b) for a, b in zip(s, r)])
    np.testing.assert_allclose(batch, [_mmrv_loops(list(a), list(b)) for a, b in zip(s, r)], atol=1e-12)
    assert np.isnan(rank_violation.mmrv([0.1, np.nan], [0.2, 0.3]))  # a draw with a missing rate


# -- resampling ------------------------------------------------------------------------------------------------------
def test_the_resampler_is_reproducible_and_draws_with_replacement():
    idx = resample.indices(10, 200, seed=7)
    assert idx.shape == (200, 10) and idx.min() >= 0 and idx.max() <= 9
    np.testing.assert_array_equal(idx, resample.indices(10, 200, seed=7))
    assert not np.array_equal(idx, resample.indices(10, 200, seed=8))
    assert any(len(set(row)) < 10 for row in idx)  # with replacement: units repeat within a draw
    w = resample.multiplicities(10, 200, seed=7)
    assert np.all(w.sum(1) == 10) and (w > 1).any() and (w == 0).any()
    np.testing.assert_array_equal(w, resample.counts_of(idx, 10))  # the same draws, counted
    # the generator is consumed as the report always has: one integers(0, n, (draws, n)) call
    np.testing.assert_array_equal(idx, np.random.default_rng(7).integers(0, 10, size=(200, 10)))
    with pytest.raises(ValueError):
        resample.multiplicities(0, 5, 0)


def test_the_percentile_interval_counts_nan_draws():
    iv = interval.percentile(np.r_[np.arange(101.0), np.nan])
    assert (iv["lo"], iv["hi"], iv["nan_draws"]) == (pytest.approx(2.5), pytest.approx(97.5), 1)
    none = interval.summary(0.5, [np.nan, np.nan])
    assert none["value"] == 0.5 and math.isnan(none["lo"]) and math.isnan(none["hi"]) and none["nan_draws"] == 2


# -- floor and ceiling -----------------------------------------------------------------------------------------------
def test_the_policy_blind_floor_gives_every_policy_its_groups_mean():
    r = np.array([[[0.2, 0.1], [0.6, np.nan], [0.9, 0.5]]])  # [B, P, C]
    f = floor.policy_blind(r, ["a", "a", "b"])
    np.testing.assert_allclose(f, [[[0.4, 0.1], [0.4, 0.1], [0.9, 0.5]]])  # nan: no rate, left out of the mean


@pytest.mark.parametrize("n", [2, 3, 7, 10])
def test_split_half_condition_halves_are_disjoint_and_equal(n):
    a, b = split_half.condition_halves(n, 100, seed=1)
    assert a.shape == b.shape == (100, n)
    assert np.all(a * b == 0) and np.all(a.sum(1) == n // 2) and np.all(b.sum(1) == n // 2)
    assert set(np.unique(a)) | set(np.unique(b)) <= {0.0, 1.0}
    np.testing.assert_array_equal(a, split_half.condition_halves(n, 100, seed=1)[0])


def test_split_half_group_halves_are_disjoint_per_group_and_draw():
    sizes = [2, 5, 36]
    halves = split_half.group_halves(sizes, 40, seed=4)
    for m, (first, second) in zip(sizes, halves):
        assert first.shape == second.shape == (40, m // 2)
        for f, s in zip(first, second):
            assert len(set(f)) == len(f) and not set(f) & set(s) and set(f) | set(s) <= set(range(m))
    again = split_half.group_halves(sizes, 40, seed=4)
    assert all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(halves, again))
    rng = np.random.default_rng(4)  # consumed group by group, draw by draw: one permutation each
    want = [np.array([rng.permutation(m) for _ in range(40)]) for m in sizes]
    assert all(np.array_equal(h[0], w[:, :m // 2]) for h, w, m in zip(halves, want, sizes))
    groups = [np.random.default_rng(m).random((m, 2)) for m in sizes]  # [m, C] per group
    a, b = split_half.group_half_means(groups, 40, seed=4)
    assert a.shape == b.shape == (40, 3, 2)
    np.testing.assert_allclose(a[:, 1], groups[1][halves[1][0]].mean(1))  # the same halves, averaged
    np.testing.assert_allclose(b[:, 2], groups[2][halves[2][1]].mean(1))


def test_the_ceilings_point_is_the_median_of_its_splits():
    assert split_half.point(np.array([0.1, np.nan, 0.5, 0.3])) == pytest.approx(0.3)
    assert math.isnan(split_half.point(np.array([np.nan, np.nan])))


# -- the floor of the package ------------------------------------------------------------------------------------------
STDLIB_OK = ("__future__", "warnings", "statistics")  # statistics: the normal quantile of the Wilson interval


def test_stats_imports_numpy_only():
    for path in sorted((Path(__file__).resolve().parents[1] / "sc3_jax" / "stats").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            for name in names:
                assert name.split(".")[0] in ("numpy", *STDLIB_OK), f"{path.name} imports {name}"
