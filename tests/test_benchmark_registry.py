"""The benchmark registry (sc3_jax/evaluation/benchmark.py): built-in names, aliases, one-line refusals, and a benchmark
defined outside the package (tests/toy_benchmark.py, named ``toy_benchmark:BENCHMARK``) that `sc3 sweep`, `sc3 report`
and `sc3 diagnose` run end to end with no file of sc3_jax naming it, on test_any_robot.py's tiny bimanual model."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import toy_benchmark
from sc3_jax.evaluation import benchmark
from sc3_jax.evaluation.benchmark import Benchmark
from sc3_jax.cli import main
from sc3_jax.core.errors import UserError
from test_any_robot import bimanual  # noqa: F401  (the fixture: imported store + trained tiny model)

TOY = "toy_benchmark:BENCHMARK"


def _one_line(e) -> str:
    msg = str(e.value)
    assert msg and "\n" not in msg, msg
    return msg


# -- the registry ----------------------------------------------------------------------------------------------------
def test_names_list_the_built_in_benchmarks_and_bench_is_bussing():
    assert {"bussing", "so101"} <= set(benchmark.names())
    assert benchmark.get("bench") is benchmark.get("bussing")
    assert benchmark.canonical("bench") == "bussing" and benchmark.canonical(TOY) == TOY
    bussing, so101 = benchmark.get("bussing"), benchmark.get("so101")
    assert bussing.name == "bussing" and so101.name == "so101"
    from sc3_jax.benchmarks.bussing.hooks import object_pixels, perception_scorer
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig
    assert bussing.scene is object_pixels and bussing.outcome_scorer is perception_scorer
    assert bussing.sweep_config is SweepConfig and callable(bussing.named_policy)
    assert set(so101.measures) == {"objects", "arm"} and so101.outcome_scorer is None


def test_the_sweeps_read_from_the_sources_are_the_benchmarks_that_have_one():
    """`sc3 sweep`'s subcommands come from the registry (names read from the sources, for `sc3 --help`): every
    built-in name or alias whose benchmark has a sweep, README command 1's bench first, then episodes."""
    from sc3_jax.commands import sweep as sweep_cmd

    everything = benchmark.names() + list(benchmark.ALIASES)
    assert set(benchmark.sweeps()) == {n for n in everything if benchmark.get(n).sweep_config is not None}
    assert list(sweep_cmd.SUBCOMMANDS) == [*benchmark.sweeps(), "episodes"] and benchmark.sweeps()[0] == "bench"
    assert benchmark.sweep_configs() == {n: benchmark.get(n).sweep_config for n in benchmark.sweeps()}


@pytest.mark.parametrize("name, says", [
    ("nope", "unknown benchmark 'nope': known are bussing, so101, bench (= bussing), or package.module:attr"),
    ("no_such_module:BENCHMARK", "cannot import 'no_such_module'"),
    ("toy_benchmark:NOPE", "'toy_benchmark' has no attribute 'NOPE'"),
    ("toy_benchmark:NOT_ONE", "object is not a sc3_jax.evaluation.benchmark.Benchmark"),
    (":x", "expected package.module:attr")])
def test_an_unknown_or_wrong_name_is_one_line(name, says):
    with pytest.raises(UserError) as e:
        benchmark.get(name)
    assert says in _one_line(e)


def test_a_module_attr_benchmark_resolves():
    assert benchmark.get(TOY) is toy_benchmark.BENCHMARK and benchmark.get(TOY).scene is toy_benchmark.bright


def test_the_interface_refuses_half_a_sweep_and_is_read_only():
    with pytest.raises(TypeError, match="both, or neither"):
        Benchmark(name="x", run_sweep=lambda cfg: None)
    b = Benchmark(name="x", measures={"objects": toy_benchmark.bright})
    assert b.scene is toy_benchmark.bright and b.run_sweep is None and Benchmark(name="y").scene is None
    with pytest.raises(TypeError):
        b.measures["arm"] = toy_benchmark.dark


def test_the_commands_refuse_an_unknown_benchmark_in_one_line(capsys, tmp_path):
    assert main(["sweep", "nope:X", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "cannot import 'nope'" in err and "\n" not in err
    assert main(["sweep", "nope"]) == 2  # a name without a colon: the usage, listing the subcommands
    assert "unknown subcommand 'nope'" in capsys.readouterr().err
    from sc3_jax.commands.diagnose import benchmark_hooks
    assert benchmark_hooks("none") == (None, {})
    assert benchmark_hooks(TOY) == (None, {"objects": toy_benchmark.bright, "dark": toy_benchmark.dark})


def test_a_store_records_its_benchmark_and_a_damaged_record_is_one_line(tmp_path):
    from sc3_jax.commands.report import scene_of

    assert benchmark.recorded(tmp_path) is None and scene_of(str(tmp_path)) is None  # no benchmark: no objects row
    assert scene_of(str(tmp_path), "bussing") is benchmark.get("bussing").scene
    benchmark.record(tmp_path, "bench")
    assert benchmark.recorded(tmp_path) == "bussing"
    benchmark.record(tmp_path, TOY)
    with pytest.raises(UserError, match="add --benchmark"):  # a store names no code to import
        scene_of(str(tmp_path))
    assert scene_of(str(tmp_path), TOY) is toy_benchmark.bright
    assert scene_of(str(tmp_path), "so101") is benchmark.get("so101").scene  # --benchmark beats the record
    for bad in ("[1]", '{"benchmark": 3}', "{", '{"benchmark": "gone_module:B"}'):
        (tmp_path / benchmark.STORE_FILE).write_text(bad)
        with pytest.raises(UserError) as e:
            scene_of(str(tmp_path))
        assert str(tmp_path) in _one_line(e)


def test_sweep_help_of_a_module_attr_benchmark_lists_its_options(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    with pytest.raises(SystemExit) as e:
        main(["sweep", TOY, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "toy benchmark's sweep" in text and "--world-model" in text and "--episode-seconds" in text


# -- a toy benchmark end to end: sweep, report, diagnose ---------------------------------------------------------------
@pytest.fixture(scope="module")
def toy_swept(bimanual, tmp_path_factory):  # noqa: F811
    tmp, store = bimanual[0], bimanual[4]
    out = tmp_path_factory.mktemp("toy") / "out"
    toy_benchmark.CALLS.update(scene=0, scorer=0, named=[])
    assert main(["sweep", TOY, "--world-model", str(tmp / "run"), "--data", str(store.root), "--out", str(out)]) == 0
    return tmp / "run", store, out, dict(toy_benchmark.CALLS)


def test_sc3_sweep_runs_a_module_attr_benchmark(toy_swept, capsys):
    _, _, out, calls = toy_swept
    assert json.loads((out / benchmark.STORE_FILE).read_text()) == {"benchmark": TOY}
    assert set(calls["named"]) == {"hold", "reach"} and calls["scorer"] >= 4 and calls["scene"] > 0
    recs = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert {r["policy"] for r in recs} == {"hold", "reach"} and len(recs) == 4
    assert all(set(r["outcomes"]) == {"success", "moved"} for r in recs)
    t = json.loads((out / "report" / "report.json").read_text())
    assert t["real"]["sources"] == [str(out / "real.csv")]
    assert t["permanence"]  # the objects-kept row, read with the toy's scene measure


def test_sc3_report_imports_a_benchmark_only_when_its_command_line_names_it(toy_swept, tmp_path, capsys):
    _, _, out, _ = toy_swept
    toy_benchmark.CALLS["scene"] = 0
    # OUT/benchmark.json names the toy, code outside the package: a store is data, so it is refused in one line
    assert main(["report", str(out), "--out", str(tmp_path / "rep"), "--draws", "50"]) == 2
    err = capsys.readouterr().err
    assert f"add --benchmark {TOY}" in err and err.count("\n") == 1 and toy_benchmark.CALLS["scene"] == 0
    assert main(["report", str(out), "--out", str(tmp_path / "rep"), "--draws", "50", "--benchmark", TOY]) == 0
    assert toy_benchmark.CALLS["scene"] > 0  # the toy's measure, named on the command line
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["permanence"]
    assert f"report: {tmp_path / 'rep' / 'report.md'}" in capsys.readouterr().out


def test_a_store_that_records_no_benchmark_reports_without_an_objects_kept_row(toy_swept, tmp_path):
    """No benchmark's objects are guessed at: the same store (its real and imagined frames kept) without
    benchmark.json reports every row but objects kept."""
    import shutil

    _, _, out, _ = toy_swept
    bare = tmp_path / "bare"
    shutil.copytree(out, bare, ignore=shutil.ignore_patterns("report"))
    (bare / benchmark.STORE_FILE).unlink()
    toy_benchmark.CALLS["scene"] = 0
    assert main(["report", str(bare), "--out", str(tmp_path / "rep"), "--draws", "50"]) == 0
    t = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert "permanence" not in t and t["real"]["sources"] and toy_benchmark.CALLS["scene"] == 0


def test_sc3_diagnose_takes_a_module_attr_benchmark(toy_swept, tmp_path, capsys):
    run, store, _, _ = toy_swept
    res = tmp_path / "diagnose.json"
    assert main(["diagnose", "--world-model", str(run), "--data", str(store.root), "--benchmark", TOY,
                 "--episodes", "1", "--stages", "open_loop", "--batch", "1", "--out", str(res), "--no-progress"]) == 0
    kept = json.loads(res.read_text())["permanence"]
    assert {r["measure"] for r in kept["rows"]} == {"objects", "dark"}  # the toy's measures, by their names
    assert "no outcome scorer" in capsys.readouterr().out  # the toy has none: outcome reproduction says so


def test_a_subprocess_names_the_toy_by_pythonpath(tmp_path):
    """Outside pytest, tests/ is on the path only through PYTHONPATH, as a lab's package would be."""
    here = str(Path(__file__).parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([here, os.environ.get("PYTHONPATH", "")])}
    code = f"from sc3_jax.evaluation import benchmark; print(benchmark.get({TOY!r}).name)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.strip() == "toy"
