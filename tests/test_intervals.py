"""Paired bootstrap intervals (a hand-computed case and a slow reference loop), the held-out tau (never moved by
evaluation results), the report's interval tables, the frame degradations."""
import dataclasses
import json
import math

import numpy as np
import pytest

from sc3_jax.evaluation import bootstrap, calibrate, degrade, intervals, report, report_bench
from sc3_jax.measures import metrics
from sc3_jax.benchmarks.bussing import sweep
from sc3_jax.evaluation.results import ResultsStore, seed_blocks
from sc3_jax.stats import correlation, interval, rank_violation, resample

CRITERIA = ("language", "lifting", "placing")  # the simulated benchmark's, as its scorers name them


# ---------------------------------------------------------------------------------------------------------------
# bootstrap
# ---------------------------------------------------------------------------------------------------------------
def test_bootstrap_hand_computed_case():
    """Two policies, two initial conditions, one object each; the four resamples of n = 2 enumerated by hand.

    real:      policy A passes everything on IC 0 and fails lifting on IC 1; policy B passes language on IC 0 only.
    evaluator: A as real; B passes language (only) on both ICs."""
    real = np.array([[[1, 1, 1], [1, 0, 0]], [[1, 0, 0], [0, 0, 0]]], float)  # [P, n, C] cumulative passes
    ev = np.array([[[1, 1, 1], [1, 0, 0]], [[1, 0, 0], [1, 0, 0]]], float)
    counts = np.ones((2, 2))
    w = resample.counts_of(np.array([[0, 0], [0, 1], [1, 0], [1, 1]]), 2)
    np.testing.assert_array_equal(w, [[2, 0], [1, 1], [1, 1], [0, 2]])
    re_r, ev_r = bootstrap.rates(real, counts, w), bootstrap.rates(ev, counts, w)
    np.testing.assert_allclose(re_r[1], [[1, .5, .5], [.5, 0, 0]])
    np.testing.assert_allclose(ev_r[3], [[1, 0, 0], [1, 0, 0]])
    s, r = ev_r.reshape(4, -1), re_r.reshape(4, -1)
    # draw (2, 0): identical vectors; (1, 1): sum xy = 0.75, sxx = 1, syy = 17/24; (0, 2): r = (2/3) / sqrt(10/9)
    np.testing.assert_allclose(correlation.pearson(s, r), [1.0, 0.75 / np.sqrt(17 / 24), 0.75 / np.sqrt(17 / 24),
                                                           2 / np.sqrt(10)])
    # MMRV: (1, 1): A-language (ev tie with B-language, real 1 > 0.5) violated by 0.5 -> 0.5 / 6; (0, 2): by 1 -> 1/6
    np.testing.assert_allclose(rank_violation.mmrv(s, r), [0.0, 0.5 / 6, 0.5 / 6, 1 / 6])
    for b in range(4):  # and the scalar definitions agree
        assert correlation.pearson(s[b], r[b]) == pytest.approx(metrics.pearson(s[b], r[b]))
        assert rank_violation.mmrv(s[b], r[b]) == pytest.approx(metrics.mmrv(s[b], r[b]))
    assert np.isnan(correlation.pearson(np.ones(3), np.arange(3.0)))  # a constant side, as metrics.pearson
    iv = interval.percentile(np.r_[np.arange(101.0), np.nan])
    assert (iv["lo"], iv["hi"], iv["nan_draws"]) == (pytest.approx(2.5), pytest.approx(97.5), 1)
    w = resample.multiplicities(7, 100, seed=3)
    assert w.shape == (100, 7) and np.all(w.sum(1) == 7) and np.array_equal(w, resample.multiplicities(7, 100, 3))


def test_evaluator_rows_match_a_slow_reference_loop():
    """The vectorised paired bootstrap equals resampling per-object rows draw by draw through metrics.faithfulness."""
    rng = np.random.default_rng(0)
    pols, split_of, n, draws = ["a", "b", "c", "d"], ["in_distribution"] * 2 + ["out_of_distribution"] * 2, 6, 40
    p_ok = {"a": .9, "b": .4, "c": .7, "d": .2}
    real, ev = {}, {}
    for p in pols:
        for i in range(n):
            for store, q in ((real, p_ok[p]), (ev, p_ok[p] * .8)):
                objs = [dict(object=f"o{j}", **{c: bool(rng.random() < q ** (k + 1))
                                                for k, c in enumerate(CRITERIA)}) for j in range(3)]
                store[p, i] = {"policy": p, "split": split_of[pols.index(p)], "seed": i, "objects": objs}
    seeds = list(range(n))
    rows = intervals.evaluator_rows(intervals.grid(real, pols, seeds, CRITERIA),
                                    {"online": intervals.grid(ev, pols, seeds, CRITERIA)}, split_of, draws, seed=5)
    w = resample.multiplicities(n, draws, 5)
    splits = ("in_distribution", "overall")
    slow, minus_floor = {"pearson": [], "mmrv": []}, {(s, m): [] for s in splits for m in ("pearson", "mmrv")}
    for b in range(draws):
        picks = [i for i in range(n) for _ in range(int(w[b, i]))]
        rows_of = lambda recs: [dict(r, episode=(i, k)) for k, i in enumerate(picks) for p in pols  # noqa: E731
                                for r in calibrate.object_rows(recs[p, i], recs[p, i]["objects"])]
        f = calibrate.faith(rows_of(ev), rows_of(real))
        real_rates = metrics.success_rates_by_split(rows_of(real))
        floor = report_bench._faith_rates(report_bench._policy_blind(real_rates), real_rates)  # the same draw's guess
        for m in slow:
            slow[m].append(f["overall"][m])
        for s, m in minus_floor:
            minus_floor[s, m].append(f[s][m] - floor[s][m])
    for m in slow:
        cell = rows["online"]["splits"]["overall"][m]
        assert (cell["lo"], cell["hi"]) == pytest.approx(tuple(np.nanpercentile(slow[m], [2.5, 97.5])))
    # versus(): against the reference itself as the other evaluator (r 1, MMRV 0 in every draw), on the same resamples
    ref_grid, ev_grid = intervals.grid(real, pols, seeds, CRITERIA), intervals.grid(ev, pols, seeds, CRITERIA)
    self_diff = intervals.versus(ref_grid, ev_grid, ref_grid, split_of, draws, seed=5)["overall"]
    for m, perfect in (("pearson", 1.0), ("mmrv", 0.0)):
        want = np.nanpercentile(np.array(slow[m]) - perfect, [2.5, 97.5])
        assert (self_diff[m]["lo"], self_diff[m]["hi"]) == pytest.approx(tuple(want))
    zero = intervals.versus(ref_grid, ev_grid, ev_grid, split_of, draws, seed=5)["in_distribution"]["pearson"]
    assert (zero["value"], zero["lo"], zero["hi"]) == (0.0, 0.0, 0.0)
    for s, m in minus_floor:  # paired: evaluator and floor on one resample per draw
        diff = rows["online"]["vs_floor"][s][m]
        assert (diff["lo"], diff["hi"]) == pytest.approx(tuple(np.nanpercentile(minus_floor[s, m], [2.5, 97.5])))
        assert diff["value"] == pytest.approx(rows["online"]["splits"][s][m]["value"] -
                                              rows["policy_blind"]["splits"][s][m]["value"])
    full = calibrate.faith([r for k in real for r in calibrate.object_rows(ev[k], ev[k]["objects"])],
                           [r for k in real for r in calibrate.object_rows(real[k], real[k]["objects"])])
    assert rows["online"]["splits"]["overall"]["pearson"]["value"] == pytest.approx(full["overall"]["pearson"])
    assert set(rows) == {"online", "policy_blind", "ceiling"} and "split-half" in rows["ceiling"]["method"]


def test_a_case_missing_on_one_side_leaves_both_sides():
    """A partial sweep: a (policy, condition) without its online rollout is left out of the real side too, so the
    rows equal those of both grids with that case removed (and rates stay rates: MMRV <= 1)."""
    rng = np.random.default_rng(1)
    pols, split_of, n = ["a", "b", "c"], ["in_distribution"] * 3, 8
    passes = lambda: rng.integers(0, 4, (3, n, 3)).cumsum(-1)[..., ::-1].astype(float)  # noqa: E731
    real, ev = (passes(), np.full((3, n), 3.0)), (passes(), np.full((3, n), 3.0))
    run = np.ones((3, n))
    run[2, 5:] = 0  # policy c's last 3 online rollouts not run yet
    dropped = lambda g: (g[0] * run[..., None], g[1] * run)  # noqa: E731
    partial = dropped(ev)
    got = intervals.evaluator_rows(real, {"online": partial}, split_of, 50, seed=3)["online"]
    want = intervals.evaluator_rows(dropped(real), {"online": partial}, split_of, 50, seed=3)["online"]
    assert got == want
    assert 0 <= got["splits"]["in_distribution"]["mmrv"]["hi"] <= 1


# ---------------------------------------------------------------------------------------------------------------
# held-out tau and the report
# ---------------------------------------------------------------------------------------------------------------
POLICIES = {"pa": "in_distribution", "pb": "in_distribution", "pc": "out_of_distribution",
            "pd": "out_of_distribution"}
U_RAW = [0.01, 0.03, 0.06]  # cuts: inf/0.1/0.07 -> 3 chunks, 0.05 -> 2, 0.02 and 0.01 -> 1


def _objs(rng, q):
    out = []
    for j in range(3):
        passed = {c: bool(rng.random() < q ** (k + 1)) for k, c in enumerate(CRITERIA)}
        out.append({"object": f"o{j}", "destination": "bin", **passed, "outcome": metrics.outcome_category(passed)})
    return out


ALL_PASS = [{"object": f"o{j}", "destination": "bin", "language": True, "lifting": True, "placing": True,
             "outcome": "no_failure"} for j in range(3)]


def _store(root, good_cut_calib: int, eval_variant: int):
    """A synthetic results store: the calibration block's online outcomes equal the real ones at cut
    ``good_cut_calib`` (every other cut: all pass, a constant evaluator); the evaluation block's online outcomes are
    random, drawn from ``eval_variant``."""
    cfg = sweep.SweepConfig(out=str(root), episodes=4, calibration_episodes=3, ceiling_episodes=2,
                            taus=(math.inf, 0.1, 0.07, 0.05, 0.02, 0.01))
    store = ResultsStore(root, cfg.to_json())
    blocks = seed_blocks(cfg)
    rng = np.random.default_rng(0)
    ev_rng = np.random.default_rng(100 + eval_variant)
    q = {"pa": .9, "pb": .5, "pc": .8, "pd": .3}
    recs = []
    for p, split in POLICIES.items():
        base = {"policy": p, "split": split, "task": "bussing"}
        for block, seeds in blocks.items():
            for s in seeds:
                real = _objs(rng, q[p])
                recs.append({**base, "id": f"{p}/{s}_real", "mode": "real", "seed": s, "objects": real,
                             "perception": real, "perception_degraded": {"blur": real}})
                if block == "ceiling":
                    continue
                if block == "calibration":
                    cuts = [real if c == good_cut_calib else ALL_PASS for c in range(4)]
                    u = U_RAW
                else:
                    cuts = [_objs(ev_rng, q[p]) for _ in range(4)]
                    u = list(ev_rng.uniform(0.0, 0.12, 3))
                recs.append({**base, "id": f"{p}/{s}_online", "mode": "online", "seed": s, "objects": cuts[-1],
                             "objects_by_cut": cuts, "u_raw": u, "u": [x * 100 for x in u], "num_chunks": 3})
    store.append(recs)
    return root


def test_tau_is_chosen_on_calibration_seeds_only(tmp_path):
    base = report.compute(_store(tmp_path / "a", good_cut_calib=2, eval_variant=0), draws=50)
    assert base["tau"]["chosen"] == "0.05" and base["tau"]["units"] == "raw"
    other_eval = report.compute(_store(tmp_path / "b", good_cut_calib=2, eval_variant=1), draws=50)
    assert other_eval["termination"] != base["termination"]  # the evaluation results did change ...
    assert json.dumps(other_eval["tau"]) == json.dumps(base["tau"])  # ... and tau (and its table) did not move
    # the calibration results, and only they, move it (the larger of two equally good taus: terminate less)
    moved = report.compute(_store(tmp_path / "c", good_cut_calib=1, eval_variant=0), draws=50)
    assert moved["tau"]["chosen"] == "0.02"
    # the calibrated row is the evaluation's online rollouts cut at tau*
    cut = next(e for e in base["termination"] if e["tau"] == "0.05")["faithfulness"]["overall"]["pearson"]
    assert base["faithfulness"]["physics"]["online_tau"]["splits"]["overall"]["pearson"]["value"] == \
        pytest.approx(cut)
    assert calibrate.choose_tau(base["tau"]["calibration"], "in_distribution") == 0.05  # a pure function of the calibration table
    with pytest.raises(ValueError, match="calibration"):
        calibrate.choose_tau([])


def test_report_prints_every_row_with_its_interval(tmp_path):
    t = report.compute(_store(tmp_path / "s", good_cut_calib=2, eval_variant=0), draws=50)
    md = report.markdown(t)
    assert t["protocol"]["evaluation"] == {"n": 4, "seeds": [10_000_000, 10_000_003],
                                           "rollouts": {"real": 16, "offline": 0, "online": 16}}
    for ref in ("physics", "perception"):
        rows = t["faithfulness"][ref]
        assert {"online", "online_tau", "policy_blind", "ceiling"} <= set(rows)
        assert "second real set, 2 conditions" in rows["ceiling"]["method"]
        for split in ("in_distribution", "out_of_distribution", "overall"):
            for m in ("pearson", "mmrv"):
                cell = rows["online"]["splits"][split][m]
                assert cell["lo"] <= cell["hi"]
            assert set(rows["online"]["per_criterion"][split]) == set(CRITERIA)
    assert "real_perception" in t["faithfulness"]["physics"]
    for name in ("noise ceiling", "policy-blind (floor)", "online (calibrated tau*)", "same instrument",
                 "end to end", "POST HOC", "(chosen)", "Better than a guess?"):
        assert name in md
    guess = md[md.index("Better than a guess?"):].split("\n## ")[0]  # the paired-difference table, one row each
    assert [x.split(" | ")[0] for x in guess.splitlines() if x.startswith("| online")] == [
        "| online (tau = inf)", "| online (calibrated tau*)"]
    line = next(x for x in md.splitlines() if x.startswith("| noise ceiling"))
    assert line.count("[") == 6  # r and MMRV with intervals for both splits and overall
    assert set(t["scorer_agreement"]) == {"clean", "blur"}
    json.dumps(t)  # report.json


def test_seed_blocks_must_be_disjoint():
    cfg = sweep.SweepConfig(episodes=10, calibration_seed0=10_000_005)
    with pytest.raises(ValueError, match="overlap"):
        seed_blocks(cfg)
    blocks = seed_blocks(dataclasses.replace(cfg, calibration_seed0=20_000_000))
    assert blocks["evaluation"][0] == 10_000_000 and len(blocks["calibration"]) == cfg.calibration_episodes


def test_degradations_are_seeded_and_change_frames():
    frames = np.random.default_rng(0).integers(0, 256, (3, 4, 64, 64, 3), dtype=np.uint8)
    a, b = degrade.all_kinds(frames, 7), degrade.all_kinds(frames, 7)
    for k in a:
        assert a[k].shape == frames.shape and a[k].dtype == np.uint8
        np.testing.assert_array_equal(a[k], b[k])  # same seed, same degradation
        assert np.abs(a[k].astype(int) - frames).mean() > 1.0
    flat = np.full((1, 1, 16, 16, 3), 100, np.uint8)
    np.testing.assert_array_equal(degrade.blur(flat), flat)  # blur keeps a flat image
    assert not np.array_equal(degrade.patch_noise(frames, 1), degrade.patch_noise(frames, 2))


def test_a_store_without_real_rollouts_gets_no_report_and_its_sweep_keeps_them(tmp_path, monkeypatch, capsys):
    from sc3_jax.commands import sweep as sweep_cmd
    from sc3_jax.core.errors import UserError

    root = _store(tmp_path / "s", good_cut_calib=2, eval_variant=0)
    online_only = [r for r in ResultsStore(root).records() if r["mode"] == "online"]
    (root / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in online_only))
    with pytest.raises(UserError, match="no real rollouts on the evaluation seeds.*--modes real"):
        report.compute(root, draws=10)
    # `sc3 sweep bench --modes online`: the rollouts stay, the command ends well and says why there is no report
    monkeypatch.setattr(sweep, "run_sweep", lambda cfg: root)
    assert sweep_cmd.main(["bench", "--out", str(root), "--modes", "online"]) == 0
    out = capsys.readouterr().out
    assert f"rollouts: {root}; no report:" in out and not (root / "report" / "report.md").exists()
    assert len(ResultsStore(root).records()) == len(online_only)


def test_the_closing_line_says_worse_when_an_interval_excludes_0_on_the_wrong_side():
    """The archived SO-101 sweep: MMRV difference [+0.052, +0.349] is worse than the guess, not indistinguishable."""
    from sc3_jax.evaluation.report_episodes import against_floor as verdict

    worse = verdict({"pearson": {"lo": -0.9, "hi": 0.5}, "mmrv": {"lo": 0.052, "hi": 0.349}})
    assert "worse than a policy-blind guess on MMRV" in worse and "better" not in worse
    assert "include 0" in verdict({"pearson": {"lo": -0.1, "hi": 0.5}, "mmrv": {"lo": -0.1, "hi": 0.2}})
    assert verdict({"pearson": {"lo": 0.1, "hi": 0.5}, "mmrv": {"lo": -0.3, "hi": -0.1}}).endswith("on r and MMRV")
