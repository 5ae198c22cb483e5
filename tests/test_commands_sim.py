"""``sc3 sim SUBCOMMAND``: every option's --help text sits under its own flag, the spellings from before the move
(``sc3 sim ...``, ``python -m sc3_jax.benchmarks.bussing.zoo_train|measure ...``) still parse, a wrong subcommand is a usage
error
listing them, and the cheap subcommands run and say what their numbers mean."""
from __future__ import annotations

import ast
import json
import re

import pytest

from sc3_jax.benchmarks.bussing.commands import sim
from sc3_jax.commands import parse
from test_commands_help import ROOT, _help_text, _leaves, _misplaced


@pytest.mark.parametrize("name", sorted(sim.SUBCOMMANDS))
def test_help_gives_every_option_its_own_docstring(name, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")  # one column of boxes (see test_commands_help)
    args = sim.SUBCOMMANDS[name]
    text = _help_text(["sim", name, "--help"], capsys)
    assert f"sc3 sim {name}" in text and args.__doc__.strip().splitlines()[0] in text
    assert not _misplaced(text, list(_leaves(args)), f"sc3 sim {name} --help")


def test_group_help_lists_every_subcommand_with_its_description(capsys):
    assert sim.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name, args in sim.SUBCOMMANDS.items():
        assert re.search(rf"^\s+{re.escape(name)}\s+{re.escape(args.__doc__.strip().splitlines()[0])}$", out, re.M)


@pytest.mark.parametrize("argv", [[], ["bogus"], ["train"], ["--out", "x"]])
def test_a_missing_or_unknown_subcommand_is_rc_2_with_the_list(argv, capsys):
    assert sim.main(argv) == 2
    err = capsys.readouterr().err
    assert "error" in err and all(f"  {name} " in err for name in sim.SUBCOMMANDS)


@pytest.mark.parametrize("argv, expected", [
    # sc3 sim ... as it was under argparse
    (["demos", "--out", "d", "--episodes", "5", "--seed", "11", "--grasp-noise", "0.04", "--release-noise", "0.08",
      "--wrong-destination-prob", "0.4", "--action-noise", "0.012", "--image-size", "32", "48", "--control-hz", "10",
      "--n-objects", "2", "--policy", "bus_bc_full", "--allow-swap-all"],
     sim.Demos(out="d", episodes=5, seed=11, grasp_noise=0.04, release_noise=0.08, wrong_destination_prob=0.4,
               action_noise=0.012, image_size=(32, 48), control_hz=10, n_objects=2, policy="bus_bc_full",
               allow_swap_all=True)),
    (["demos", "--out", "d"], sim.Demos(out="d")),
    (["demos-stats", "--data", "a", "b"], sim.DemosStats(("a", "b"))),
    (["demos-stats", "--data", "a", "--zoo-real", "None"], sim.DemosStats(("a",), None)),
    (["mixture", "--out", "m", "--episodes", "5", "--seed", "41", "--recipe", "clean", "--workers", "16", "--seconds",
      "120", "--image-size", "32", "48", "--control-hz", "10", "--n-objects", "2", "--shard", "1/4", "--no-progress"],
     sim.Mixture(out="m", episodes=5, seed=41, recipe="clean", workers=16, seconds=120.0, image_size=(32, 48),
                 control_hz=10, n_objects=2, shard="1/4", progress=False)),
    (["mixture", "--out", "m"], sim.Mixture(out="m")),
    (["eval", "--policy", "rev_bc_full", "--task", "reverse", "--episodes", "3", "--out", "o", "--no-videos",
      "--image-size", "32", "32"], sim.Eval("rev_bc_full", "reverse", 3, "o", False, (32, 32))),
    (["eval", "--policy", "zero"], sim.Eval("zero", "bussing", 36, None, True, (64, 64))),
    (["zoo-train", "--workdir", "w", "--out", "o"], sim.ZooTrain("w", "o", None)),
    (["zoo-eval", "--out", "o", "--episodes", "4", "--no-videos", "--policies", "bus_bc_full", "rev_bc_full"],
     sim.ZooEval("o", 4, False, ("bus_bc_full", "rev_bc_full"))),
    (["zoo-eval", "--out", "o"], sim.ZooEval("o", 36, True, None)),
    (["zoo-list"], sim.ZooList()),
    # python -m sc3_jax.benchmarks.bussing.zoo_train train|list|manifest, python -m sc3_jax.benchmarks.bussing.measure
    (["zoo-train", "--workdir", "w", "--runs", "clean", "small"], sim.ZooTrain("w", None, ("clean", "small"))),
    (["zoo-train"], sim.ZooTrain("/tmp/sc3_zoo", None, None)),
    (["zoo-manifest"], sim.ZooManifest(None)),
    (["measure", "--episodes", "5"], sim.Measure(5)),
])
def test_the_spellings_from_before_still_parse(argv, expected):
    assert parse(sim.SUBCOMMANDS[argv[0]], argv[1:], f"sim {argv[0]}") == expected


@pytest.mark.parametrize("argv", [["demos"], ["demos", "--out", "d", "--control-hz", "15"], ["eval"],
                                  ["mixture", "--out", "m", "--recipe", "reverse"],
                                  ["eval", "--policy", "x", "--task", "stack"], ["zoo-list", "stray"]])
def test_missing_or_bad_options_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as e:
        sim.main(argv)
    assert e.value.code == 2 and capsys.readouterr().err


def test_the_library_modules_keep_no_command_line():
    """The benchmark's modules are a library; its command lines live in commands/ beside them."""
    libs = sorted((ROOT / "sc3_jax" / "benchmarks" / "bussing").glob("*.py"))
    assert {"measure", "zoo_train", "policy_eval"} <= {p.stem for p in libs}
    for path in libs:
        lib = path.stem
        tree = ast.parse(path.read_text())
        imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert "argparse" not in imported, f"sim/{lib}.py imports argparse"
        assert not any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body), f"sim/{lib}.py: main"
        assert "__main__" not in ast.unparse(tree), f"sim/{lib}.py keeps a __main__ block"


def test_zoo_list_and_manifest_say_what_they_hold(tmp_path, capsys):
    from sc3_jax.benchmarks.bussing.zoo import ZOO

    assert sim.main(["zoo-list"]) == 0
    out = capsys.readouterr().out
    assert all(re.search(rf"^{n}\s+{e.task}\s+{re.escape(e.weights)}", out, re.M) for n, e in ZOO.items())
    assert f"{len(ZOO)} zoo policies" in out and "sc3 sim eval --policy NAME" in out
    assert sim.main(["zoo-manifest", "--out", str(tmp_path / "z")]) == 0
    assert f"wrote {tmp_path / 'z' / 'zoo.json'}" in capsys.readouterr().out
    assert set(json.loads((tmp_path / "z" / "zoo.json").read_text())["policies"]) == set(ZOO)


def test_demos_writes_the_store_and_explains_its_fractions(tmp_path, capsys):
    store = tmp_path / "demos"
    assert sim.main(["demos", "--out", str(store), "--episodes", "1", "--image-size", "32", "32"]) == 0
    out = capsys.readouterr().out
    s = json.loads(out[:out.index("\n}\n") + 2])  # the summary object, then the explanation
    assert s["written"] == 1 and s["success"]["n_objects"] == 3
    tail = out[out.index("\n}\n"):]
    assert f"wrote 1 scripted expert episodes to the episode store {store}" in tail
    for crit, meaning in [("language", "never brought into the wrong container"), ("lifting", "gripper raised"),
                          ("placing", "inside their instructed container")]:
        assert re.search(rf"{crit}\s+{s['success'][crit]:.2f}\s+share of objects.*{meaning}", tail)
    assert sim.main(["demos-stats", "--data", str(store)]) == 0
    out = capsys.readouterr().out
    assert f"1 episodes (3 objects) in {store}" in out and "all_objects_swapped: 0 episodes" in out


def test_demos_refuses_a_policy_that_is_not_a_bussing_zoo_policy(tmp_path):
    from sc3_jax.core.errors import UserError

    with pytest.raises(UserError, match="--policy rev_bc_full: not a bussing zoo policy"):
        sim.main(["demos", "--out", str(tmp_path / "d"), "--episodes", "1", "--policy", "rev_bc_full"])
    assert not (tmp_path / "d").exists()


def test_eval_and_measure_say_what_their_numbers_are(monkeypatch, capsys):
    from sc3_jax.benchmarks.bussing import measure, policy_eval

    rates = {"language": 0.9, "lifting": 0.8, "placing": 0.7, "outcome/language": 0.1, "outcome/lifting": 0.1,
             "outcome/placing": 0.1, "outcome/no failure": 0.7, "n_objects": 6}
    monkeypatch.setattr(policy_eval, "evaluate_policy", lambda policy, task, episodes, out, **kw: {
        "policy": "zero", "task": task, "episodes": episodes, "seed0": 10_000_000, "success": rates, "seconds": 1.0})
    assert sim.main(["eval", "--policy", "zero", "--episodes", "2"]) == 0
    out = capsys.readouterr().out
    assert "zero on bussing: 2 episodes (simulator seeds 10000000-10000001), 6 objects" in out
    assert re.search(r"placing\s+0.70\s+share of objects", out) and "0.10 / 0.10 / 0.10 / 0.70" in out
    assert "nothing written (--out DIR" in out
    monkeypatch.setattr(measure, "measure_all", lambda episodes: {"demos_per_hour": 1.0, "episodes": episodes})
    assert sim.main(["measure", "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    assert '"episodes": 3' in out and "success rates over 3 episodes" in out and "render_ms_*" in out


def test_mixture_writes_and_demos_stats_sets_it_beside_the_zoo(tmp_path, capsys):
    from sc3_jax.benchmarks.bussing.mixture import CATEGORIES

    store = tmp_path / "mix"
    assert sim.main(["mixture", "--out", str(store), "--episodes", "2", "--image-size", "16", "16",
                     "--no-progress"]) == 0
    out = capsys.readouterr().out
    s = json.loads(out[:out.index("\n}\n") + 2])
    assert s["written"] == 2 and sum(s["sources"].values()) == 2
    assert f"wrote 2 episodes of the failure_rich mixture to the episode store {store}" in out
    assert sim.main(["demos-stats", "--data", str(store)]) == 0
    out = capsys.readouterr().out
    assert "2 episodes (6 objects)" in out and all(f"  {k}: " in out for k in CATEGORIES)
    # the data's rows, then the zoo's real ones from the archived 72-condition sweep
    assert re.search(r"^  all\s+2\s+6\s", out, re.M)
    assert re.search(r"^  bus_confused\s+72\s+216\s+0\.84\s+0\.41\s+0\.41\s", out, re.M)
    assert re.search(r"^  in distribution \(bussing\)\s+504\s+1512\s", out, re.M)
    assert "keeps the reverse split out of distribution" in out
    assert sim.main(["demos-stats", "--data", str(store), "--zoo-real", "None"]) == 0
    assert "bus_confused" not in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["mixture", "--out", "OUT", "--shard", "4/4"], "--shard 4/4: write I/N"),
    (["mixture", "--out", "OUT", "--seed", "100"], "seed 100: keep below 100"),
    (["demos-stats", "--data", "OUT", "--zoo-real", "/nonexistent"], "--zoo-real"),
    (["demos-stats", "--data", "/nonexistent"], "--data /nonexistent: no such directory"),
])
def test_mixture_and_stats_refuse_bad_options_in_one_line(argv, message, tmp_path):
    from sc3_jax.core.errors import UserError

    (tmp_path / "OUT").mkdir()
    with pytest.raises(UserError, match=re.escape(message)):
        sim.main([str(tmp_path / a) if a == "OUT" else a for a in argv])


def test_the_mixture_command_offers_every_recipe():
    import typing

    from sc3_jax.benchmarks.bussing.mixture import RECIPES

    assert set(typing.get_args(typing.get_type_hints(sim.Mixture)["recipe"])) == set(RECIPES)
