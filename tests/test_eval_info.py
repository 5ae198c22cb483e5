"""A sweep store's rates in lerobot-eval's eval_info.json shape (sc3_jax/evaluation/eval_info.py), with a Wilson 95%
interval beside each rate (sc3_jax/stats/interval.py): the interval against published values, the shape against
lerobot 0.6.1's keys, the counting on hand-made records of both record forms, and a shipped SO-101 store end to end."""
import json
from pathlib import Path

import numpy as np
import pytest

from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import eval_info
from sc3_jax.stats.interval import wilson

ROOT = Path(__file__).resolve().parents[1]
LEROBOT_GROUP_KEYS = {"avg_sum_reward", "avg_max_reward", "pc_success", "n_episodes", "video_paths",
                      "predicted_video_paths"}  # lerobot 0.6.1 eval_policy_all's per_group / overall entries


@pytest.mark.parametrize("k, n, lo, hi", [(5, 10, 0.2366, 0.7634), (0, 10, 0.0, 0.2775), (10, 10, 0.7225, 1.0),
                                          (81, 263, 0.2553, 0.3662)])
def test_the_wilson_interval_matches_published_values(k, n, lo, hi):
    ci = wilson(k, n)
    assert ci["lo"] == pytest.approx(lo, abs=1e-4) and ci["hi"] == pytest.approx(hi, abs=1e-4)
    assert np.isnan(wilson(0, 0)["lo"])
    with pytest.raises(ValueError):
        wilson(3, 2)


def _ic(policy, seed, success, block="evaluation"):
    return {"id": f"{policy}/{seed}_online", "mode": "online", "policy": policy, "seed": seed, "block": block,
            "episode": f"ep{seed}", "outcomes": {"success": success, "moved": True}}


def test_rates_count_the_evaluation_block_in_lerobots_shape():
    recs = [_ic("a", i, s) for i, s in enumerate([True, True, False, True])] + \
        [_ic("a", 4, False, "calibration"), _ic("b", 0, False)]
    info = eval_info.eval_info(recs, "a", suite="so101")
    assert set(info) == {"per_task", "per_group", "overall", "sc3"}
    assert LEROBOT_GROUP_KEYS <= set(info["overall"]) and LEROBOT_GROUP_KEYS <= set(info["per_group"]["so101"])
    task = info["per_task"][0]
    assert (task["task_group"], task["task_id"]) == ("so101", 0)
    assert task["metrics"]["successes"] == [True, True, False, True]  # the calibration episode is not counted
    assert task["metrics"]["episodes"] == ["ep0", "ep1", "ep2", "ep3"]
    o = info["overall"]
    assert o["pc_success"] == 75.0 and o["n_episodes"] == 4 and o["avg_sum_reward"] == 0.75
    ci = wilson(3, 4)
    assert o["pc_success_ci95"] == pytest.approx([100 * ci["lo"], 100 * ci["hi"]])
    assert eval_info.eval_info(recs, "a", criterion="moved")["overall"]["pc_success"] == 100.0


def test_per_object_records_group_by_split_and_task_and_need_every_object():
    def bench(seed, task, split, placed):
        return {"id": f"p/{seed}_online", "mode": "online", "policy": "p", "seed": seed, "task": task, "split": split,
                "objects": [{"object": f"o{j}", "placing": v, "lifting": True} for j, v in enumerate(placed)]}
    recs = [bench(0, "bussing", "in_distribution", [True, True]), bench(1, "bussing", "in_distribution", [True, False]),
            bench(2, "reverse", "out_of_distribution", [True])]
    info = eval_info.eval_info(recs, "p", criterion="placing", blocks={"evaluation": [0, 1, 2]})
    by = {(t["task_group"], t["task_id"]): t["metrics"] for t in info["per_task"]}
    assert by[("in_distribution", "bussing")]["successes"] == [True, False]
    assert by[("out_of_distribution", "reverse")]["pc_success"] == 100.0
    assert info["overall"]["n_episodes"] == 3 and info["overall"]["pc_success"] == pytest.approx(200 / 3)
    with pytest.raises(UserError) as e:
        eval_info.eval_info(recs, "p")  # no "success" among per-object criteria
    assert "not 'success'" in str(e.value) and "\n" not in str(e.value)


def test_a_shipped_sweep_store_writes_one_file_per_policy_with_its_rate(tmp_path):
    from sc3_jax.evaluation.results import ResultsStore

    src = ROOT / "docs" / "stores" / "so101_v3_sweep36"
    records = ResultsStore(src).records()
    written = eval_info.write(src, tmp_path)
    policies = sorted({r["policy"] for r in records if r["mode"] == "online"})
    assert sorted(p.parent.name for p in written if p.parent.parent.name == "online") == policies
    for path in written:
        info = json.loads(path.read_text())
        mine = [r for r in records if r["policy"] == path.parent.name and r["mode"] == path.parent.parent.name
                and r.get("block", "evaluation") == "evaluation"]
        k = sum(r["outcomes"]["success"] for r in mine)
        assert info["overall"]["n_episodes"] == len(mine) > 0
        assert info["overall"]["pc_success"] == pytest.approx(100 * k / len(mine))
        assert info["sc3"]["store"] == str(src)
    with pytest.raises(UserError, match="no online records of policy 'nobody'"):
        eval_info.eval_info(records, "nobody")


def test_sc3_report_writes_eval_info_beside_its_report(tmp_path, capsys):
    import shutil

    from sc3_jax import cli

    store = tmp_path / "store"
    shutil.copytree(ROOT / "docs" / "stores" / "so101_v3_sweep36", store)
    assert cli.main(["report", str(store), "--real", str(store / "real.csv"), "--out", str(tmp_path / "r"),
                     "--videos", "0", "--draws", "200"]) == 0
    files = sorted((tmp_path / "r" / "eval_info").rglob("eval_info.json"))
    assert len(files) == 8 and "8 eval_info.json in lerobot-eval's shape" in capsys.readouterr().out
    assert {"per_task", "overall"} <= set(json.loads(files[0].read_text()))
