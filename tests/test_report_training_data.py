"""The report's section on what the world model was trained on (``data_stats.json`` shipped beside it), and the
planner's FLOP count where a backend's lowered module gives none."""
import json

import pytest

from sc3_jax.core import xla_cost
from sc3_jax.evaluation import report_bench, report_bench_render


def _stats(episodes=4, tasks=("bussing",)):
    src = {"lifted": 6, "placed": 4, "wrong_container": 2, "dropped": 1, "missed": 5, "objects": 12,
           "episodes": episodes}
    return {"episodes": episodes, "objects": 12, "tasks": {t: episodes for t in tasks},
            "objects_in_other_container": {"0 of 3": 2, "1 of 3": 2}, "all_objects_swapped": 0,
            "outcomes": {"sources": {"dc_expert": src}, "all": src}}


def test_the_training_data_section_names_the_swept_tasks_the_data_never_shows(tmp_path):
    assert report_bench.training_data(str(tmp_path), {"bussing"}) is None  # no file: no section
    (tmp_path / "data_stats.json").write_text(json.dumps(_stats()))
    d = report_bench.training_data(str(tmp_path), {"bussing", "reverse"})
    assert d["unseen_tasks"] == ["reverse"] and d["episodes"] == 4
    title, header, rows = report_bench_render._training_data_table(d)
    assert "never shows: reverse" in title and "1 of 3: 2" in title
    assert header[3:] == ["lifted", "placed", "wrong_container", "dropped", "missed"]
    # shares of the source's objects: placed + wrong + dropped + missed = 1
    assert rows[0][:3] == ["dc_expert", "4", "12"] and rows[0][3:] == ["0.50", "0.33", "0.17", "0.08", "0.42"]
    d = report_bench.training_data(str(tmp_path), {"bussing"})
    assert d["unseen_tasks"] == [] and "never shows" not in report_bench_render._training_data_table(d)[0]


class _Lowered:
    def __init__(self, lowered_cost, compiled_cost):
        self.lowered_cost, self.compiled_cost = lowered_cost, compiled_cost

    def cost_analysis(self):
        return self.lowered_cost

    def compile(self):
        return type("C", (), {"cost_analysis": lambda s: self.compiled_cost})()


def test_flops_fall_back_to_the_compiled_count_where_the_lowered_module_gives_none():
    assert xla_cost.flops(_Lowered({"flops": 5.0}, {"flops": 7.0}), compiled=False) == 5.0
    assert xla_cost.flops(_Lowered({"flops": 5.0}, [{"flops": 7.0}]), compiled=True) == 7.0
    assert xla_cost.flops(_Lowered(None, [{"flops": 7.0}]), compiled=False) == 7.0  # CUDA under jax 0.11
    with pytest.raises(RuntimeError, match="no FLOP count"):
        xla_cost.flops(_Lowered(None, None), compiled=False)
