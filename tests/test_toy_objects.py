"""A benchmark with per-object criteria and two splits, defined in tests/ (toy_objects.py, named
``toy_objects:BENCHMARK``), runs through the same sweep engine, report and tau calibration as the simulated benchmark:
`sc3 sweep`, `sc3 report` and `sc3 diagnose`, on test_any_robot.py's tiny bimanual model, with no file of sc3_jax
naming it."""
import json

import pytest

import toy_objects
from sc3_jax.cli import main
from test_any_robot import bimanual  # noqa: F401  (the fixture: imported store + trained tiny model)

TOY = "toy_objects:BENCHMARK"


@pytest.fixture(scope="module")
def swept(bimanual, tmp_path_factory):  # noqa: F811
    tmp, store = bimanual[0], bimanual[4]
    out = tmp_path_factory.mktemp("toy_objects") / "out"
    assert main(["sweep", TOY, "--world-model", str(tmp / "run"), "--data", str(store.root), "--out", str(out)]) == 0
    return tmp / "run", store, out


def _records(out):
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]


def test_the_engine_writes_its_real_and_imagined_rollouts_per_object(swept):
    _, _, out = swept
    recs = _records(out)
    real = [r for r in recs if r["mode"] == "real"]
    online = [r for r in recs if r["mode"] == "online"]
    # 4 policies x (3 evaluation + 2 calibration + 2 ceiling) real; x (3 + 2) online
    assert len(real) == 4 * 7 and len(online) == 4 * 5
    assert {r["split"] for r in recs} == {"seen", "novel"}
    for r in real + online:
        assert [o["object"] for o in r["objects"]] == list(toy_objects.ARMS)
        assert all(set(toy_objects.CRITERIA) <= set(o) for o in r["objects"])
    for r in online:  # every cut scored, the whole rollout last
        assert len(r["objects_by_cut"]) == r["num_chunks"] + 1 and r["objects_by_cut"][-1] == r["objects"]
    # a record's outcomes are written with sorted keys: the sweep records the order of the criteria and splits
    saved = json.loads((out / "sweep.json").read_text())
    assert (saved["criteria"], saved["splits"]) == (["reached", "held"], ["seen", "novel"])


def test_the_report_reads_the_toys_criteria_and_splits_and_chooses_tau_on_its_first(swept):
    _, _, out = swept
    t = json.loads((out / "report" / "report.json").read_text())
    assert t["criteria"] == list(toy_objects.CRITERIA)
    assert [s for _, s in t["policies"]] == ["seen", "seen", "novel", "novel"]  # the recorded order, not by name
    rows = t["faithfulness"]["physics"]
    assert {"online", "online_tau", "policy_blind", "ceiling"} <= set(rows)
    assert set(rows["online"]["splits"]) == {"seen", "novel", "overall"}
    assert set(rows["online"]["per_criterion"]["seen"]) == set(toy_objects.CRITERIA)
    assert t["tau"]["rule"].startswith("max seen r") and t["tau"]["chosen"] is not None
    assert [e["tau"] for e in t["tau"]["calibration"]] == ["inf", "1.0", "0.3", "0.1"]
    assert {s: r["ranked_by"] for s, r in t["ranking"].items()} == {"seen": "held", "novel": "held"}
    assert set(t["reproduction"]["online"]) <= {"reached", "held", "no_failure"}
    md = (out / "report" / "report.md").read_text()
    assert "Reached / held, cumulative." in md and "seen r" in md and "novel r" in md


def test_sc3_report_and_diagnose_take_it_by_name(swept, tmp_path):
    run, store, out = swept
    assert main(["report", str(out), "--out", str(tmp_path / "rep"), "--draws", "50", "--benchmark", TOY]) == 0
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["criteria"] == list(toy_objects.CRITERIA)
    res = tmp_path / "diagnose.json"
    assert main(["diagnose", "--world-model", str(run), "--data", str(store.root), "--benchmark", TOY,
                 "--episodes", "1", "--stages", "open_loop", "--batch", "1", "--out", str(res), "--no-progress"]) == 0
    assert {r["measure"] for r in json.loads(res.read_text())["permanence"]["rows"]} == {"objects"}
