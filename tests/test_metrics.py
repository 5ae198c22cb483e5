"""Faithfulness metrics against hand-computed values (every expected number below is worked out by hand)."""
import dataclasses
import math
import warnings

import numpy as np
import pytest

from sc3_jax.measures.metrics import (
    categories,
    criteria_of,
    cumulative_passes,
    faithfulness,
    group_by_split,
    mmrv,
    outcome_categories,
    outcome_category,
    pearson,
    psnr,
    reproduction_counts,
    reproduction_rate,
    success_rates,
    success_rates_by_split,
    termination_rate,
)


CRITERIA = ("language", "lifting", "placing")  # a benchmark's (the simulated one's), as its scorers name them


def test_an_outcome_carries_its_criteria_in_their_order():
    outcome = {"object": "cup", "destination": "bin", "language": True, "lifting": False, "placing": np.bool_(False),
               "outcome": "lifting"}
    assert criteria_of(outcome) == CRITERIA  # its booleans; the strings name the object and its category
    assert categories(CRITERIA) == ("language", "lifting", "placing", "no_failure")
    assert outcome_category(outcome) == "lifting" and cumulative_passes(outcome)["language"]
    assert outcome_category({"touched": True, "moved": False}) == "moved"  # any benchmark's criteria


# ---------------------------------------------------------------- Pearson

def test_pearson_hand_three_points():
    # x = [-1, 0, 1], y = [-1, 1, 0]: sum xy = 1, sum x^2 = sum y^2 = 2 -> r = 1 / 2
    assert pearson(evaluator=[1.0, 2.0, 3.0], real=[1.0, 3.0, 2.0]) == pytest.approx(0.5, abs=1e-12)
    # x = [-.3, -.1, .4], y = [-.3, .1, .2]: sum xy = .16, sum x^2 = .26, sum y^2 = .14
    r = pearson([0.2, 0.4, 0.9], [0.1, 0.5, 0.6])
    assert r == pytest.approx(0.16 / math.sqrt(0.26 * 0.14), abs=1e-12)
    assert r == pytest.approx(0.838628, abs=1e-6)


def test_pearson_perfect_and_anti():
    assert pearson([0.1, 0.2, 0.4], [0.3, 0.5, 0.9]) == pytest.approx(1.0, abs=1e-12)
    assert pearson([1, 2, 3], [3, 2, 1]) == pytest.approx(-1.0, abs=1e-12)
    assert pearson([0.1, 0.2, 0.4], [0.3, 0.5, 0.9]) <= 1.0  # clipped, never 1 + eps


def test_pearson_symmetric():
    a, b = [0.2, 0.4, 0.9, 0.1], [0.1, 0.5, 0.6, 0.3]
    assert pearson(a, b) == pytest.approx(pearson(b, a), abs=1e-15)


def test_pearson_constant_vectors_are_nan_without_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(pearson([0.5, 0.5, 0.5], [0.1, 0.4, 0.9]))  # blind evaluator
        assert math.isnan(pearson([0.1, 0.4, 0.9], [0.3, 0.3, 0.3]))  # constant real
        assert math.isnan(pearson([0.3, 0.3], [0.3, 0.3]))  # both constant
        # 0.1 repeated: mean is not exactly 0.1 in floating point, still detected as constant
        assert math.isnan(pearson([0.1] * 7, [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]))


@pytest.mark.parametrize("fn", [pearson, mmrv])
def test_validation(fn):
    with pytest.raises(ValueError, match="same length"):
        fn([0.1, 0.2, 0.3], [0.1, 0.2])
    with pytest.raises(ValueError, match="at least 2"):
        fn([0.1], [0.2])
    with pytest.raises(ValueError, match="at least 2"):
        fn([], [])
    with pytest.raises(ValueError, match="real: non-finite values at indices \\[1\\]"):
        fn([0.1, 0.2], [0.1, float("nan")])
    with pytest.raises(ValueError, match="evaluator: non-finite"):
        fn([0.1, float("inf")], [0.1, 0.2])
    with pytest.raises(ValueError, match="1-D"):
        fn([[0.1, 0.2]], [[0.1, 0.2]])
    with pytest.raises(ValueError, match="evaluator"):
        fn(["a", "b"], [0.1, 0.2])


# ---------------------------------------------------------------- MMRV

def _mmrv_loops(s, r):
    """Literal transcription of the MMRV formula (metrics.py's docstring), used only as a cross-check."""
    n = len(s)
    total = 0.0
    for i in range(n):
        worst = 0.0
        for j in range(n):
            if (s[i] > s[j]) != (r[i] > r[j]):
                worst = max(worst, abs(r[i] - r[j]))
        total += worst
    return total / n


def test_mmrv_perfect_ranking_is_zero():
    assert mmrv([0.1, 0.5, 0.9], [0.2, 0.3, 0.8]) == 0.0
    assert mmrv([0.9, 0.1, 0.5], [0.8, 0.2, 0.3]) == 0.0  # order of points is irrelevant


def test_mmrv_single_swap_sized_by_real():
    # Points 0 and 1 swapped: evaluator gap 0.1, real gap 0.2. Both points see a violation of size 0.2 (real),
    # point 2 none -> (0.2 + 0.2 + 0) / 3.
    assert mmrv(evaluator=[0.2, 0.1, 0.8], real=[0.3, 0.5, 0.9]) == pytest.approx(0.4 / 3, abs=1e-12)


def test_mmrv_takes_max_not_sum():
    # i=0 violates against j=1 (0.4) and j=2 (0.6) -> 0.6; i=1 against j=0 -> 0.4; i=2 against j=0 -> 0.6
    # (i=2 vs j=1 agrees) -> 1.6 / 3. (A sum over j would give 2.0 / 3.)
    assert mmrv([0.9, 0.1, 0.2], [0.1, 0.5, 0.7]) == pytest.approx(1.6 / 3, abs=1e-12)


def test_mmrv_evaluator_ties_with_different_real_values_are_violations():
    # S0 == S1 but R1 > R0: at i=1, (S1 > S0) = False != (R1 > R0) = True -> 0.4; i=0 and i=2 fine.
    assert mmrv([0.5, 0.5, 0.9], [0.2, 0.6, 0.9]) == pytest.approx(0.4 / 3, abs=1e-12)


def test_mmrv_real_ties_cost_nothing():
    # R0 == R1 but S1 > S0: a violation at i=1 of size |R1 - R0| = 0.
    assert mmrv([0.2, 0.6, 0.9], [0.5, 0.5, 0.9]) == 0.0


def test_mmrv_constant_vectors():
    # constant evaluator: every point above the real minimum is violated by its gap to it: (0 + .3 + .8) / 3
    assert mmrv([0.5, 0.5, 0.5], [0.1, 0.4, 0.9]) == pytest.approx(1.1 / 3, abs=1e-12)
    # constant real: all sizes are 0
    assert mmrv([0.1, 0.4, 0.9], [0.5, 0.5, 0.5]) == 0.0
    assert mmrv([0.3, 0.3], [0.3, 0.3]) == 0.0


def test_mmrv_argument_order_matters():
    s, r = [0.1, 0.2], [0.9, 0.5]
    # reversed ranking: sizes come from the real gap 0.4 at both points -> 0.4; swapped: evaluator gap 0.1
    assert mmrv(evaluator=s, real=r) == pytest.approx(0.4, abs=1e-12)
    assert mmrv(evaluator=r, real=s) == pytest.approx(0.1, abs=1e-12)
    # strictness is asymmetric too: evaluator tie over a real gap of 0.6 -> (0 + 0.6) / 2 = 0.3;
    # swapped, it becomes a real tie, which costs nothing.
    assert mmrv(evaluator=[0.5, 0.5], real=[0.2, 0.8]) == pytest.approx(0.3, abs=1e-12)
    assert mmrv(evaluator=[0.2, 0.8], real=[0.5, 0.5]) == 0.0


def test_mmrv_matches_literal_formula_with_ties():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = int(rng.integers(2, 12))
        s = rng.integers(0, 5, n) / 4.0  # coarse grid: many ties
        r = rng.integers(0, 5, n) / 4.0
        assert mmrv(s, r) == pytest.approx(_mmrv_loops(s, r), abs=1e-12)


# ---------------------------------------------------------------- criteria, categories, success rates

@pytest.mark.parametrize("passed, expected", [
    ((True, True, True), "no_failure"),
    ((False, True, True), "language"),
    ((False, False, False), "language"),
    ((True, False, True), "lifting"),
    ((True, True, False), "placing"),
    ([1, 1, 0], "placing"),
    (np.array([True, False, False]), "lifting"),
    ({"placing": True, "lifting": False, "language": True}, "lifting"),
    ({"language": True, "lifting": True, "placing": True, "policy": "x"}, "no_failure"),  # extra keys ignored
])
def test_outcome_category(passed, expected):
    assert outcome_category(passed, CRITERIA) == expected


def test_outcome_category_refuses_bad_input():
    with pytest.raises(ValueError, match="3 booleans"):
        outcome_category((True, True), CRITERIA)
    with pytest.raises(ValueError, match="missing criteria \\['placing'\\]"):
        outcome_category({"language": True, "lifting": True}, CRITERIA)
    with pytest.raises(ValueError, match="boolean"):
        outcome_category(("False", True, True), CRITERIA)  # a truthy string must not pass as True
    with pytest.raises(ValueError, match="boolean"):
        outcome_category((True, 2, True), CRITERIA)
    with pytest.raises(ValueError, match="criteria named"):
        outcome_category((True, True, True))  # a sequence says nothing of which criteria it holds


def test_cumulative_passes():
    assert cumulative_passes((True, False, True), CRITERIA) == {"language": True, "lifting": False, "placing": False}
    assert cumulative_passes((False, True, True), CRITERIA) == {"language": False, "lifting": False, "placing": False}
    assert cumulative_passes((True, True, True), CRITERIA) == {"language": True, "lifting": True, "placing": True}


def _rec(policy, split, episode, obj, lang, lift, place):
    return {"policy": policy, "split": split, "episode": episode, "object": obj,
            "language": lang, "lifting": lift, "placing": place}


RECORDS = [
    _rec("A", "bussing", 0, "fork", True, True, True),
    _rec("A", "bussing", 0, "can", True, False, True),   # placed without lifting: counts as not placed
    _rec("A", "bussing", 1, "fork", False, True, True),  # wrong object: fails everything
    _rec("A", "bussing", 1, "can", True, True, False),
    _rec("B", "bussing", 0, "fork", True, True, True),
    _rec("B", "bussing", 0, "can", True, True, True),
    _rec("A", "reverse", 0, "fork", True, False, False),
    _rec("A", "reverse", 0, "can", False, False, False),
    _rec("B", "reverse", 0, "fork", True, True, False),
    _rec("B", "reverse", 0, "can", True, True, True),
]


def test_success_rates_are_cumulative():
    rates = success_rates(RECORDS[:6])
    # A: language 3/4; lifting 2/4 (not 3/4); placing 1/4 (not 2/4). B: everything passes.
    assert rates == {("A", "language"): 0.75, ("A", "lifting"): 0.5, ("A", "placing"): 0.25,
                     ("B", "language"): 1.0, ("B", "lifting"): 1.0, ("B", "placing"): 1.0}


def test_success_rates_by_split_and_grouping():
    groups = group_by_split(RECORDS)
    assert list(groups) == ["bussing", "reverse"] and [len(g) for g in groups.values()] == [6, 4]
    by_split = success_rates_by_split(RECORDS)
    assert by_split["bussing"] == success_rates(RECORDS[:6])
    assert by_split["reverse"] == {("A", "language"): 0.5, ("A", "lifting"): 0.0, ("A", "placing"): 0.0,
                                   ("B", "language"): 1.0, ("B", "lifting"): 1.0, ("B", "placing"): 0.5}
    # pooled over both splits: A language (3 + 1) / 6
    assert success_rates(RECORDS)[("A", "language")] == pytest.approx(4 / 6)


def test_success_rates_accepts_attribute_records():
    @dataclasses.dataclass
    class Row:
        policy: str
        split: str
        episode: int
        object: str
        language: bool
        lifting: bool
        placing: bool

    rows = [Row("P", "bussing", 0, "fork", True, True, False), Row("P", "bussing", 1, "fork", True, False, True)]
    assert success_rates(rows) == {("P", "language"): 1.0, ("P", "lifting"): 0.5, ("P", "placing"): 0.0}


def test_success_rates_refuses_bad_records():
    with pytest.raises(ValueError, match="duplicate case"):
        success_rates([RECORDS[0], dict(RECORDS[0])])
    bad = dict(RECORDS[0])
    del bad["lifting"]
    with pytest.raises(ValueError, match="record 1: missing field 'lifting'"):
        success_rates([RECORDS[1], bad])
    with pytest.raises(ValueError, match="boolean"):
        success_rates([{**RECORDS[0], "placing": "yes"}])
    with pytest.raises(ValueError, match="no records"):
        success_rates([])


def test_outcome_categories_from_records():
    cats = outcome_categories(RECORDS[:4])
    assert cats == {("A", "bussing", 0, "fork"): "no_failure", ("A", "bussing", 0, "can"): "lifting",
                    ("A", "bussing", 1, "fork"): "language", ("A", "bussing", 1, "can"): "placing"}


# ---------------------------------------------------------------- faithfulness

def test_faithfulness_per_split_and_overall():
    ev = {"bussing": {("A", "c"): 0.1, ("B", "c"): 0.2, ("C", "c"): 0.3},
          "reverse": {("A", "c"): 0.0, ("B", "c"): 0.1, ("C", "c"): 0.2}}
    # real dicts in a different key order: pairing must go by key, not position
    real = {"reverse": {("C", "c"): 0.2, ("B", "c"): 0.1, ("A", "c"): 0.0},
            "bussing": {("B", "c"): 0.3, ("A", "c"): 0.1, ("C", "c"): 0.2}}
    out = faithfulness(ev, real, ["bussing", "reverse"])
    assert list(out) == ["bussing", "reverse", "overall"]
    # bussing: S = [.1, .2, .3], R = [.1, .3, .2] -> r = 1/2; B and C swapped by a real gap .1 -> 0.2 / 3
    assert out["bussing"]["pearson"] == pytest.approx(0.5, abs=1e-12)
    assert out["bussing"]["mmrv"] == pytest.approx(0.2 / 3, abs=1e-12)
    assert out["bussing"]["n"] == 3
    assert out["reverse"]["pearson"] == pytest.approx(1.0, abs=1e-12)
    assert out["reverse"]["mmrv"] == 0.0
    # overall: 6 points, both means 0.15: sum xy = .045, sum x^2 = sum y^2 = .055 -> r = 9/11.
    # MMRV: bussing-B is violated by bussing-C (.1) and by reverse-C (evaluator tie .2/.2, real .3 > .2: .1);
    # bussing-C by bussing-B (.1); the reverse-C vs bussing-C real tie costs 0 -> (.1 + .1) / 6.
    assert out["overall"]["pearson"] == pytest.approx(9 / 11, abs=1e-12)
    assert out["overall"]["mmrv"] == pytest.approx(0.2 / 6, abs=1e-12)
    assert out["overall"]["n"] == 6
    # splits selects: only one split -> overall equals it
    one = faithfulness(ev, real, ["reverse"])
    assert list(one) == ["reverse", "overall"] and one["overall"] == one["reverse"]
    # default: evaluator's splits in its order
    assert list(faithfulness(ev, real)) == ["bussing", "reverse", "overall"]


def test_faithfulness_errors():
    ev = {"bussing": {("A", "c"): 0.1, ("B", "c"): 0.2}}
    with pytest.raises(ValueError, match="only in evaluator: \\[\\('B', 'c'\\)\\]"):
        faithfulness(ev, {"bussing": {("A", "c"): 0.1, ("C", "c"): 0.3}})
    with pytest.raises(ValueError, match="real_rates: no split 'bussing'"):
        faithfulness(ev, {"reverse": {("A", "c"): 0.1, ("B", "c"): 0.2}})
    with pytest.raises(ValueError, match="reserved"):
        faithfulness({"overall": ev["bussing"]}, {"overall": ev["bussing"]})
    with pytest.raises(ValueError, match="split 'bussing': need at least 2"):
        faithfulness({"bussing": {("A", "c"): 0.1}}, {"bussing": {("A", "c"): 0.1}})


def test_faithfulness_end_to_end_from_records():
    real = success_rates_by_split(RECORDS)
    out = faithfulness(real, real)  # an evaluator that reproduces reality exactly
    for split in ("bussing", "reverse", "overall"):
        assert out[split]["mmrv"] == 0.0
        assert out[split]["pearson"] == pytest.approx(1.0, abs=1e-12)
    assert out["overall"]["n"] == 12


# ---------------------------------------------------------------- reproduction rates

def test_reproduction_rate():
    real = {1: "language", 2: "language", 3: "lifting", 4: "no_failure", 5: "placing"}
    ev = {1: "language", 2: "lifting", 3: "lifting", 4: "placing", 5: "placing"}
    assert reproduction_rate(real, ev, CRITERIA) == {"language": 0.5, "lifting": 1.0, "placing": 1.0,
                                                     "no_failure": 0.0}
    assert reproduction_counts(real, ev, CRITERIA) == {"language": (1, 2), "lifting": (1, 1), "placing": (1, 1),
                                                       "no_failure": (0, 1)}
    # the direction matters: per *real* category
    assert reproduction_rate(ev, real, CRITERIA) == {"language": 1.0, "lifting": 0.5, "placing": 0.5}
    # a category with no real case is absent
    assert "placing" not in reproduction_rate({1: "lifting", 2: "lifting"}, {1: "lifting", 2: "placing"}, CRITERIA)


def test_reproduction_rate_errors():
    with pytest.raises(ValueError, match="only in real: \\[2\\]"):
        reproduction_rate({1: "language", 2: "lifting"}, {1: "language"}, CRITERIA)
    with pytest.raises(ValueError, match="unknown category 'no failure'"):
        reproduction_rate({1: "no failure"}, {1: "language"}, CRITERIA)
    with pytest.raises(ValueError, match="no cases"):
        reproduction_rate({}, {}, CRITERIA)


# ---------------------------------------------------------------- PSNR

def test_psnr_hand_values_uint8():
    target = np.zeros((2, 2, 2, 3), np.uint8)  # [T, H, W, C]
    pred = target.copy()
    pred[0] = 10  # MSE 100 -> 10 log10(255^2 / 100) = 10 log10(650.25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = psnr(pred, target)
    assert out.shape == (2,)
    assert out[0] == pytest.approx(28.13080, abs=1e-4)
    assert out[1] == math.inf  # identical frame
    # uint8 must not wrap around: target - pred would be 246 in uint8
    assert psnr(target, pred)[0] == pytest.approx(28.13080, abs=1e-4)
    # one saturated pixel out of 4 (single channel): MSE 255^2 / 4 -> 10 log10(4)
    one = np.zeros((2, 2, 1), np.uint8)
    one[0, 0, 0] = 255
    assert psnr(one, np.zeros_like(one)) == pytest.approx(6.0206, abs=1e-4)


def test_psnr_float_and_views():
    target = np.full((3, 4, 2, 2, 3), 0.6, np.float32)  # [V, T, H, W, C] in [0, 1]
    pred = np.full_like(target, 0.5)  # MSE 0.01 -> 20 dB
    out = psnr(pred, target, max_value=1.0)
    assert out.shape == (3, 4)
    np.testing.assert_allclose(out, 20.0, atol=1e-4)
    assert psnr(pred, target, max_value=1.0, axis=None) == pytest.approx(20.0, abs=1e-4)


def test_psnr_errors():
    with pytest.raises(ValueError, match="same shape"):
        psnr(np.zeros((2, 2, 2, 3)), np.zeros((1, 2, 2, 3)))
    with pytest.raises(ValueError, match="exceed max_value"):
        psnr(np.full((2, 2, 3), 200, np.uint8), np.zeros((2, 2, 3), np.uint8), max_value=1.0)
    with pytest.raises(ValueError, match="finite"):
        psnr(np.full((2, 2, 3), np.nan), np.zeros((2, 2, 3)), max_value=1.0)
    with pytest.raises(ValueError, match="max_value"):
        psnr(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), max_value=0.0)


# ---------------------------------------------------------------- termination

def test_termination_rate():
    assert termination_rate([True, False, True, False]) == 0.5
    assert termination_rate([1, 1, 1, 0]) == 0.75
    assert termination_rate([[False, False, True], [False, False, False]]) == 0.5  # any step done
    with pytest.raises(ValueError, match="booleans"):
        termination_rate([0, 2])
    with pytest.raises(ValueError, match="no episodes"):
        termination_rate([])
    with pytest.raises(ValueError, match="1-D"):
        termination_rate(np.zeros((2, 2, 2), bool))
