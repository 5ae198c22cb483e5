"""``sc3 sweep so101 --lerobot-eval NAME=EVAL_INFO``: a LeRobot policy's real outcomes read from the eval_info.json
of the real ``lerobot-eval --env.type=sc3_so101`` (episode i = the sweep's condition i), not run again here."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.benchmarks.so101 import lerobot_outcomes
from sc3_jax.core.errors import UserError

# written by the real lerobot-eval 0.6.1 of an ACT in the simulator (docs/so101_curve/act/eval.sh): 36 episodes
REAL = Path(__file__).resolve().parents[1] / "docs" / "so101_curve" / "act" / "eval_info_005000.json"


def _info(successes: list[bool]) -> dict:
    info = json.loads(REAL.read_text())
    info["per_task"][0]["metrics"]["successes"] = successes
    return info


def test_the_real_lerobot_eval_file_gives_its_episodes_in_order():
    done, info = lerobot_outcomes.successes(REAL, 36)
    assert done == [False] * 36 and info["overall"]["n_episodes"] == 36
    assert lerobot_outcomes.successes(REAL, 5)[0] == [False] * 5  # the sweep's first conditions


@settings(max_examples=25, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=40), st.integers(1, 40))
def test_the_first_episodes_are_read_or_too_few_are_one_line(tmp_path_factory, successes, episodes):
    path = tmp_path_factory.mktemp("info") / "eval_info.json"
    path.write_text(json.dumps(_info(successes)))
    if episodes <= len(successes):
        assert lerobot_outcomes.successes(path, episodes)[0] == successes[:episodes]
    else:
        with pytest.raises(UserError, match=f"{len(successes)} episodes, the sweep's --episodes {episodes}") as e:
            lerobot_outcomes.successes(path, episodes)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("text, says", [
    ("not json {", "cannot read it as JSON"),
    ("[1, 2]", "not the eval_info.json of one lerobot-eval --env.type=sc3_so101"),
    (json.dumps({"per_task": [{"task_group": "so101", "metrics": {"successes": [True]}}]}), "names ['so101']"),
    (json.dumps({"per_task": [{"task_group": "sc3_so101", "metrics": {"successes": [1, 0]}}]}), "no list of successes"),
])
def test_a_file_that_is_not_our_envs_evaluation_is_one_line(tmp_path, text, says):
    path = tmp_path / "eval_info.json"
    path.write_text(text)
    with pytest.raises(UserError, match=says.replace("[", r"\[").replace("]", r"\]")) as e:
        lerobot_outcomes.successes(path, 1)
    assert "\n" not in str(e.value)


def test_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(UserError, match="cannot read it as JSON"):
        lerobot_outcomes.successes(tmp_path / "nope.json", 1)


@pytest.mark.parametrize("spec", ["act", "=x.json", "act="])
def test_a_spec_without_name_and_file_is_one_line(spec):
    with pytest.raises(UserError, match="NAME=EVAL_INFO"):
        lerobot_outcomes.parse(spec)


def test_the_file_is_kept_in_the_store_and_a_name_may_not_climb_out(tmp_path):
    info = json.loads(REAL.read_text())
    assert json.loads(lerobot_outcomes.keep(tmp_path, "act", info).read_text()) == info
    assert (tmp_path / "lerobot_eval" / "act" / "eval_info.json").is_file()
    with pytest.raises(UserError, match="outside"):
        lerobot_outcomes.keep(tmp_path, "../act", info)


# -- through the sweep's own functions (the simulator package: the so101 extra) -------------------------------------
def _sweep():
    pytest.importorskip("lerobot_env_so101")
    from sc3_jax.benchmarks.so101 import sweep
    return sweep


def test_the_sweep_takes_a_policy_by_its_recorded_name_once(tmp_path):
    sweep = _sweep()
    names = ["so_full", "act=lerobot:/ckpt/pretrained_model"]
    given = sweep.lerobot_real((f"act={REAL}",), names, 36)
    assert list(given) == ["act"] and given["act"][0] == [False] * 36
    with pytest.raises(UserError, match="'acts' is not one of the sweep's policies"):
        sweep.lerobot_real((f"acts={REAL}",), names, 36)
    with pytest.raises(UserError, match="given twice"):
        sweep.lerobot_real((f"act={REAL}", f"act={REAL}"), names, 36)


def test_given_outcomes_are_written_without_a_run_and_another_evaluation_is_refused(tmp_path, monkeypatch):
    sweep = _sweep()
    from sc3_jax.benchmarks.so101 import rollouts

    def no_run(*a, **k):
        raise AssertionError("a given policy ran in the simulator")
    monkeypatch.setattr(rollouts, "run_episodes", no_run)
    seeds = [sweep.EVAL_SEED0 + i for i in range(3)]
    args = (tmp_path, ["act=lerobot:/ckpt"], seeds, 100, (80, 80), ("workspace", "wrist"), None, 1, False)
    sweep.real_outcomes(*args, given={"act": [True, False, True]})
    with open(tmp_path / sweep.REAL_FILE, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["policy"], r["episode"], r["success"]) for r in rows] == [
        ("act", f"seed{seeds[0]}", "true"), ("act", f"seed{seeds[1]}", "false"), ("act", f"seed{seeds[2]}", "true")]
    sweep.real_outcomes(*args, given={"act": [True, False, True]})  # a rerun: the same rows, nothing added
    assert (tmp_path / sweep.REAL_FILE).read_text().count("\n") == 4
    with pytest.raises(UserError, match="holds other real outcomes of 'act'"):
        sweep.real_outcomes(*args, given={"act": [True, True, True]})


def test_a_sweep_whose_real_outcomes_all_came_from_lerobot_eval_is_described_without_a_scorer_check(tmp_path):
    # every policy given by --lerobot-eval: no real episode ran, so no scorer_check.json (the sweep ended in a raw
    # "No such file" after its rollouts)
    from sc3_jax.benchmarks.so101.benchmark import describe_sweep
    from sc3_jax.benchmarks.so101.sweep import CHECK_FILE, So101SweepConfig

    cfg = So101SweepConfig(world_model="WM", out=str(tmp_path), scorer="pkg.mod:attr", episodes=3)
    lines = describe_sweep(cfg, tmp_path)
    assert "3 simulator seeds" in lines[0] and "not checked against the simulator" in lines[1]
    (tmp_path / CHECK_FILE).write_text(json.dumps({"agreement": 0.75, "all": {"n": 4}}))
    assert describe_sweep(cfg, tmp_path)[1].endswith("agrees with the simulator on 0.75 of 4")
