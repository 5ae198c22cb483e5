"""``sc3 diagnose``'s outcome reproduction per physics category with episode-bootstrap intervals
(``diagnose_outcomes.physics_reproduction``) on hand-built rows, and ``--stages open_loop`` on the tiny copy-last
world model of test_diagnose.py: only the open-loop pass runs, the other sections and their gates read "not run", and
the JSON it writes stays readable by ``sc3 report`` / ``sc3 diagnose-table``."""
import contextlib
import io
import json
import math
import shutil

import pytest
from test_diagnose import _copy_last_model, _tiny_store

from sc3_jax.cli import main as cli
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import diagnose as dg
from sc3_jax.evaluation import diagnose_outcomes as do
from sc3_jax.evaluation.diagnose_report import NOT_RUN_NOTE, render_table, verdict

# an object per outcome category (metrics.outcome_category: the first criterion it fails)
CAT = {"language": (False, False, False), "lifting": (True, False, False), "placing": (True, True, False),
       "no_failure": (True, True, True)}


def _obj(cat):
    language, lifting, placing = CAT[cat]
    return {"name": "o", "destination": "bin", "language": language, "lifting": lifting, "placing": placing,
            "outcome": cat}


def _row(episode, pairs):
    """One episode's row: ``pairs`` of (physics category, imagined category)."""
    physics = [_obj(p) for p, _ in pairs]
    return {"episode": episode, "imagined": [_obj(i) for _, i in pairs], "real_perception": physics,
            "physics": physics, "covered": True}


# 3 episodes, 8 objects: placed 4 (3 imagined placed, 1 dropped), dropped 2 (1 dropped, 1 placed), missed 1
# (imagined wrong container), wrong container 1 (imagined so)
ROWS = [_row("a", [("no_failure", "no_failure"), ("no_failure", "no_failure"), ("placing", "placing")]),
        _row("b", [("no_failure", "placing"), ("placing", "no_failure"), ("lifting", "language")]),
        _row("c", [("no_failure", "no_failure"), ("language", "language")])]


def test_per_category_counts_fractions_and_confusion_are_exact():
    sec = do.outcome_section(ROWS, None, seed=0)
    r = sec["physics_reproduction"]
    assert (r["n_objects"], r["n_episodes"], r["draws"]) == (8, 3, do.BOOTSTRAP_DRAWS)
    cats = r["categories"]
    assert {c: cats[c]["n_objects"] for c in CAT} == {"no_failure": 4, "placing": 2, "lifting": 1, "language": 1}
    assert cats["no_failure"]["agreement"] == 0.75 and cats["placing"]["agreement"] == 0.5
    assert cats["lifting"]["agreement"] == 0.0 and cats["language"]["agreement"] == 1.0
    assert r["outcome"]["agreement"] == 5 / 8 == sec["imagined_vs_physics"]["outcome"]  # the old field agrees
    # per criterion: language differs only for the missed object imagined in the wrong container (which is not
    # lifted either, like the missed one), placing for the placed / dropped swaps
    assert {c: r["criteria"][c]["agreement"] for c in ("language", "lifting", "placing")} == \
        {"language": 7 / 8, "lifting": 1.0, "placing": 6 / 8}
    assert r["confusion"]["no_failure"] == {"language": 0, "lifting": 0, "placing": 1, "no_failure": 3}
    assert r["confusion"]["lifting"] == {"language": 1, "lifting": 0, "placing": 0, "no_failure": 0}
    assert sum(sum(row.values()) for row in r["confusion"].values()) == r["n_objects"]
    assert {c: sum(row.values()) for c, row in r["confusion"].items()} == {c: cats[c]["n_objects"] for c in CAT}
    assert not r["enough_objects"] and r["min_objects"] == do.MIN_OBJECTS
    # seeded: the same seed gives the same intervals
    assert do.physics_reproduction(ROWS, seed=0) == r


def test_intervals_contain_the_estimate_shrink_with_episodes_and_resample_episodes():
    few = do.physics_reproduction(ROWS * 2, seed=1)
    many = do.physics_reproduction(ROWS * 20, seed=1)
    for r in (few, many):
        for s in [r["outcome"], *r["criteria"].values(), *(r["categories"][c] for c in ("no_failure", "placing"))]:
            lo, hi = s["ci95"]
            assert lo <= s["agreement"] <= hi
    width = lambda s: s["ci95"][1] - s["ci95"][0]  # noqa: E731
    assert few["outcome"]["agreement"] == many["outcome"]["agreement"] == 5 / 8
    assert width(many["outcome"]) < 0.5 * width(few["outcome"])
    assert width(many["categories"]["no_failure"]) < 0.5 * width(few["categories"]["no_failure"])
    # objects of one episode move together: 10 episodes of 10 objects, every object of half of them imagined wrong.
    # Resampling episodes gives about a binomial interval of 10 (+-0.3); resampling the 100 objects would give +-0.1
    rows = [_row(str(e), [("no_failure", "no_failure" if e % 2 else "placing")] * 10) for e in range(10)]
    r = do.physics_reproduction(rows, seed=0)
    assert r["outcome"]["agreement"] == 0.5 and width(r["outcome"]) > 0.4
    # one episode: nothing to resample, no interval
    one = do.physics_reproduction(ROWS[:1], seed=0)
    assert one["draws"] == 0 and one["outcome"]["ci95"] is None and one["outcome"]["agreement"] == 1.0


def test_no_physics_labels_gives_no_reproduction_and_the_verdict_reads_the_set_size():
    uncovered = [{**r, "physics": None, "covered": False} for r in ROWS]
    assert do.outcome_section(uncovered, None)["physics_reproduction"] is None
    big = do.physics_reproduction(ROWS * 19, seed=0)  # 152 objects
    small = do.physics_reproduction(ROWS * 18, seed=0)  # 144
    assert big["enough_objects"] and not small["enough_objects"]
    for r, want in ((big, "152 objects with physics labels in 57 episodes: large enough to read per category"),
                    (small, "144 objects with physics labels in 54 episodes: too few to tell 0.67 from 0.75 "
                            f"(needs >= {do.MIN_OBJECTS})")):
        lines = verdict({"gates": [], "outcomes": {"available": True, "physics_reproduction": r}})
        assert lines[-1] == f"outcome set: {want}"


def test_outcome_categories_print_in_the_benchmarks_words_else_by_their_own_names():
    """The core knows no benchmark's words: a category is its criterion's name unless the benchmark names it
    (``Benchmark.category_names``, kept in the section); the bussing benchmark's are the simulator's."""
    from sc3_jax.evaluation import benchmark
    from sc3_jax.evaluation.diagnose_report import _outcome_lines

    plain = "\n".join(_outcome_lines(do.outcome_section(ROWS, None, seed=0))[1])
    assert "| placing | 2 |" in plain and "imagined no_failure" in plain and "dropped" not in plain
    words = benchmark.get("bussing").category_names
    named = do.outcome_section(ROWS, None, seed=0, names=words)
    assert named["category_names"] == dict(words) and "category_names" not in do.outcome_section(ROWS, None)
    text = "\n".join(_outcome_lines(named)[1])
    assert "| dropped / off target | 2 |" in text and "imagined wrong container" in text
    assert "| placing | 2 |" not in text


@pytest.fixture(scope="module")
def open_loop_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("diagnose_open_loop")
    store = _tiny_store(root / "heldout")
    wm = _copy_last_model(root)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli(["diagnose", "--world-model", str(wm), "--data", str(store.root), "--stages", "open_loop", "--out",
                  str(wm / "diagnose.json"), "--benchmark", "bussing", "--no-progress"])
    assert rc == 0
    return wm, dg.load_result(wm / "diagnose.json"), out.getvalue()


def test_open_loop_stage_runs_only_drift_and_outcomes(open_loop_run):
    _, result, text = open_loop_run
    assert result["settings"]["stages"] == ["open_loop"]
    for k in ("teacher_forced", "counterfactual", "inverse_dynamics"):
        assert result[k] == {"available": False, "note": NOT_RUN_NOTE}
    assert any(row["n_episodes"] for rows in result["drift"]["views"].values() for row in rows)
    oc = result["outcomes"]
    assert oc["available"] and oc["reference"] == "physics"
    r = oc["physics_reproduction"]
    assert r["n_objects"] == oc["imagined_vs_physics"]["n_objects"] == 6 and r["n_episodes"] == 2
    assert r["outcome"]["agreement"] == oc["imagined_vs_physics"]["outcome"]
    assert sum(sum(row.values()) for row in r["confusion"].values()) == 6
    g = {x["gate"]: x for x in result["gates"]}
    for name in dg.GATES[:3]:
        assert g[name]["pass"] is None and math.isnan(g[name]["value"]) and g[name]["note"] == NOT_RUN_NOTE
    assert g[dg.GATES[3]]["pass"] is not None and g[dg.GATES[4]]["pass"] is True
    # the printout: each skipped section one line, the reproduction table, the gates' and the set's verdicts
    assert text.startswith(render_table(result))
    assert text.count(f"\n{NOT_RUN_NOTE}\n") == 3 and "| physics category | objects |" in text
    # objects kept over the open loop (the benchmark's object pixels): a copy-last model keeps the first frame's
    # objects, as many as the recording shows from the third-person cameras (the wrist camera's change as it moves)
    kept = next(r["times"] for r in result["permanence"]["rows"] if r["stage"] == "open loop")
    assert "1 s" in kept and kept["1 s"]["rollouts"] == 2
    assert all(0.7 < kept["1 s"]["kept"][v]["value"] < 1.3 for v in result["third_person_views"]), kept["1 s"]
    assert "### Objects kept, stage by stage" in text
    assert "| not run |" in text  # the gates' pass column
    tail = text.splitlines()
    assert any(line.startswith("gates: ") and "3 not run: --stages skipped teacher_forced, inverse_dynamics, "
               "counterfactual" in line for line in tail)
    assert "outcome set: 6 objects with physics labels in 2 episodes: too few to tell 0.67 from 0.75" in text


def test_a_stage_not_named_is_a_usage_error(open_loop_run, capsys):
    wm, result, _ = open_loop_run
    with pytest.raises(SystemExit) as e:  # tyro's usage error, naming the choices
        cli(["diagnose", "--world-model", str(wm), "--data", result["data"], "--stages", "closed_loop"])
    assert e.value.code == 2 and "closed_loop" in capsys.readouterr().err
    with pytest.raises(UserError, match="name one or more of teacher_forced counterfactual open_loop"):
        dg.diagnose(wm, result["data"], stages=())


def test_report_reads_a_diagnose_json_with_skipped_stages(open_loop_run):
    from sc3_jax.evaluation import report_bench
    wm, result, _ = open_loop_run
    d = report_bench._diagnose_gates(str(wm))
    assert d["episodes"] == 2 and [g["pass"] for g in d["gates"]][:3] == [None, None, None]


def test_diagnose_table_reads_a_diagnose_json_with_skipped_stages(open_loop_run, tmp_path):
    wm, result, _ = open_loop_run
    d = tmp_path / "open_loop"
    shutil.copytree(wm, d)
    out = tmp_path / "table.md"
    assert cli(["diagnose-table", "--world-model", str(d), "--out", str(out)]) == 0
    row = out.read_text().splitlines()[2].split(" | ")
    assert row[0] == "| open_loop" and row.count("n/a") >= 5  # the teacher-forced / counterfactual / ID columns
    assert json.loads((d / "diagnose.json").read_text())["outcomes"]["physics_reproduction"]["n_objects"] == 6


def test_a_gate_that_cannot_be_measured_reads_not_measured_not_fail():
    """Issue 76: an outcome gate with nothing to measure it by (no outcome scorer: --benchmark none) printed FAIL,
    which reads as the model's fault; it reads "not measured", neither passing nor failing, with its reason."""
    from sc3_jax.evaluation import diagnose_report as dr

    skipped = {"available": False, "note": NOT_RUN_NOTE}
    result = {"third_person_views": ["left"], "views": ["left"], "teacher_forced": skipped, "drift": skipped,
              "counterfactual": skipped, "inverse_dynamics": skipped,
              "outcomes": {"available": False, "note": "no outcome scorer (--benchmark none)"}}
    result["gates"] = dr.gates(result, dg.DiagnoseConfig())
    g = {x["gate"]: x for x in result["gates"]}[dg.GATES[3]]
    assert g["pass"] is None and math.isnan(g["value"]) and g["note"] == "not measured: no outcome scorer " \
        "(--benchmark none)" and dr.word(g) == "not measured"
    lines = verdict(result)
    assert "FAIL" not in "\n".join(lines) and "1 not measured" in lines[0], lines
    assert f"  not measured {dg.GATES[3]}: no outcome scorer (--benchmark none)" in lines, lines
