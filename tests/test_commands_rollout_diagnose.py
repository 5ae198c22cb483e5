"""``sc3 rollout`` and ``sc3 diagnose`` on the tyro surface: ``--help`` gives every option its own docstring, both
commands sample a world model exactly as ``sc3 sweep bench`` does (``SweepConfig``'s defaults, not the checkpoint's own
settings), a ``--SECTION.FIELD`` override reaches the config, and an unknown option is a usage error. The runs
themselves are tested in test_rollout.py and test_diagnose.py."""
from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest
import test_commands_help
from test_diagnose import _copy_last_model, _tiny_store

from sc3_jax.cli import main
from sc3_jax.commands import diagnose as diagnose_cmd
from sc3_jax.commands import parse, parse_evaluated
from sc3_jax.commands import rollout as rollout_cmd
from sc3_jax.benchmarks.bussing.sweep import SweepConfig

COMMANDS = {"rollout": rollout_cmd, "diagnose": diagnose_cmd}


def _required(command: str, wm) -> list[str]:
    if command == "rollout":
        return ["--world-model", str(wm), "--policy", "zero", "--data", "ics.npz", "--out", "o"]
    return ["--world-model", str(wm), "--data", "heldout"]


def _config(command: str, wm, *overrides: str):
    """The config the command would evaluate the world model under (parsing only: nothing runs)."""
    mod = COMMANDS[command]
    return parse_evaluated(mod.Args, _required(command, wm) + list(overrides), command)[1]


@pytest.fixture(scope="module")
def wm(tmp_path_factory):
    """A tiny saved world model whose own sampler (3 steps, re-read in 3, 20 s) is not the sweep's."""
    path = _copy_last_model(tmp_path_factory.mktemp("commands"))
    from sc3_jax.model import checkpoint
    own = checkpoint.read_config(path)
    sweep = SweepConfig()
    assert (own.sample.steps, own.sample.inverse_steps, own.rollout.episode_seconds) != \
        (sweep.sample_steps, sweep.inverse_steps, sweep.episode_seconds)
    return path


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_gives_every_option_its_own_docstring(command, capsys, monkeypatch):
    """Each option's docstring under its own flag, and the description naming the config overrides."""
    monkeypatch.setenv("COLUMNS", "120")
    args = COMMANDS[command].Args
    text = test_commands_help._help_text([command, "--help"], capsys)
    assert " ".join(args.__doc__.split()[:6]) in text and "--SECTION.FIELD VALUE" in text
    problems = test_commands_help._misplaced(text, list(test_commands_help._leaves(args)), f"sc3 {command} --help")
    assert not problems, "\n".join(problems)


def test_rollout_diagnose_and_sweep_sample_a_world_model_alike(wm, tmp_path, monkeypatch):
    """The config `sc3 sweep bench` builds its rollouts from (caught where it constructs them) is the one both
    commands evaluate under: the same sampler steps, inverse re-read steps and U units; the horizon is the only
    difference (the benchmark's 12 s in the sweep, the world model's own in rollout and diagnose)."""
    from sc3_jax.rollout import rollout
    from sc3_jax.benchmarks.bussing import sweep
    from sc3_jax.benchmarks.bussing.zoo import zoo_names
    from sc3_jax.core.config import replace
    from sc3_jax.evaluation.world_model_defaults import Sampler

    class Built(Exception):
        pass

    def catch(cfg, *args, **kwargs):
        raise Built(cfg)

    monkeypatch.setattr(rollout, "Rollout", catch)
    with pytest.raises(Built) as e:
        sweep.run_sweep(SweepConfig(out=str(tmp_path / "sweep"), world_model=str(wm), modes=("online",),
                                    policies=(zoo_names("bussing")[0],), progress=False,
                                    workers=1))  # in this process, where Rollout is caught
    swept, defaults = e.value.args[0], Sampler()
    assert (swept.sample.steps, swept.sample.inverse_steps, swept.rollout.episode_seconds,
            swept.rollout.tau_units) == (defaults.sample_steps, defaults.inverse_steps, SweepConfig().episode_seconds,
                                         defaults.tau_units)
    from sc3_jax.model import checkpoint
    own = checkpoint.read_config(wm).rollout.episode_seconds
    for command in COMMANDS:
        cfg = _config(command, wm)
        assert cfg.rollout.episode_seconds == own, command
        assert replace(cfg, rollout=dict(episode_seconds=swept.rollout.episode_seconds)) == swept, command


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_sampler_steps_and_a_dotted_override_reach_the_config(command, wm):
    cfg = _config(command, wm, "--sample-steps", "8", "--rollout.tau", "0.05", "--rollout.episode-seconds", "6")
    assert (cfg.sample.steps, cfg.rollout.tau, cfg.rollout.episode_seconds) == (8, 0.05, 6.0)
    assert cfg.sample.inverse_steps == SweepConfig().inverse_steps  # what was not overridden keeps the sampler's
    from sc3_jax.model import checkpoint
    own = checkpoint.read_config(wm).sample
    cfg = _config(command, wm, "--sample-steps", "None", "--inverse-steps", "None")  # the model's own
    assert (cfg.sample.steps, cfg.sample.inverse_steps) == (own.steps, own.inverse_steps)


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("bad", [["--rollout.no-such-field", "1"], ["--sample.steps", "8"], ["--num-chunks", "3"]])
def test_an_unknown_option_is_a_usage_error(command, bad, wm, capsys):
    """An unknown config field, a spelling that became a --SECTION.FIELD override, and a config field that became an
    option of its own (--sample.steps: --sample-steps), are refused by name."""
    try:
        rc = main([command, *_required(command, wm), *bad])
    except SystemExit as e:  # tyro's usage error
        rc = e.code
    assert rc == 2 and bad[0] in capsys.readouterr().err


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_world_model_without_a_config_is_a_one_line_error(command, tmp_path, capsys):
    assert main([command, *_required(command, tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sc3 {command}: error: {tmp_path}: no config.json") and err.count("\n") == 1


@pytest.mark.parametrize("command, argv, expected", [
    ("rollout", ["--world-model", "wm", "--policy", "zero", "--data", "ics", "--out", "o"],
     dict(sample_steps=2, inverse_steps=1, world_model="wm", policy="zero", data="ics", out="o", step=None,
          family="native", episodes=None, start=0, task=0, batch=None, data_fps=None, seed=0, offline=False,
          perception=None, benchmark="none", learned_state=True, video=True, progress=True)),
    ("rollout", ["--world-model", "wm", "--policy", "ws://h:1", "--data", "ics", "--out", "o",
                 "--step", "5", "--family", "libero", "--episodes", "2", "--start", "1", "--task", "1",
                 "--batch", "1", "--data-fps", "10", "--seed", "3", "--offline", "--no-video", "--no-progress",
                 "--benchmark", "toy_benchmark:BENCHMARK"],
     dict(sample_steps=2, inverse_steps=1, world_model="wm", policy="ws://h:1", data="ics", out="o", step=5,
          family="libero", episodes=2, start=1, task=1, batch=1, data_fps=10.0, seed=3, offline=True,
          perception=None, benchmark="toy_benchmark:BENCHMARK", learned_state=True, video=False, progress=False)),
    ("diagnose", ["--world-model", "wm", "--data", "h", "--episodes", "4", "--cf-starts", "1", "--out", "r.json",
                  "--seed", "1", "--max-seconds", "4", "--batch", "2", "--moving-threshold", "0.1", "--horizons", "0.8",
                  "2", "--perception", "p.npz", "--no-progress", "--sample-steps", "8", "--cf-fraction", "0.25",
                  "--carry-px", "2", "--against", "wm2", "--stages", "open_loop", "dense"],
     dict(sample_steps=8, inverse_steps=1, world_model="wm", data="h", episodes=4, cf_starts=1, out="r.json",
          cf_fraction=0.25, carry_px=2.0, against="wm2",
          filmstrips=None, seed=1, max_seconds=4.0, batch=2, moving_threshold=0.1, horizons=(0.8, 2.0),
          perception="p.npz", progress=False, benchmark="none", stages=("open_loop", "dense"))),
])
def test_the_options_parse_into_their_fields(command, argv, expected):
    assert dataclasses.asdict(parse(COMMANDS[command].Args, argv, command)) == expected


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_no_command_defaults_to_a_benchmark(command):
    """Without --benchmark a model of any robot is rolled out or diagnosed with the generic measures alone: no outcome
    scorer, no scene measure, no locators, no benchmark's policy names (the bussing benchmark only when named)."""
    a = parse(COMMANDS[command].Args, _required(command, "wm"), command)
    assert a.benchmark == "none"
    bm = rollout_cmd.benchmark_of(a.benchmark)
    assert (bm.outcome_scorer, dict(bm.measures), bm.named_policy, bm.locators) == (None, {}, None, None)
    assert diagnose_cmd.benchmark_hooks(a.benchmark) == (None, {})
    assert diagnose_cmd.benchmark_locators(a.benchmark) is None


def test_the_libraries_keep_no_command_line():
    from sc3_jax.evaluation import diagnose
    assert importlib.util.find_spec("sc3_jax.rollout_cli") is None  # became sc3_jax/rollout/rollout_io.py
    assert not hasattr(diagnose, "main")


def test_u_summary_counts_the_chunks_run_and_the_episodes_stopped():
    from sc3_jax.evaluation.rollout_summary import u_summary

    u_raw = np.array([[0.01, 0.03, 0.5], [0.01, 0.01, 0.01], [0.09, 0.7, 0.7]])
    result = {"u_raw": u_raw, "u": 100 * u_raw, "terminated_at": np.array([1, -1, 0])}
    s = u_summary(result, 0.02, "raw")
    ran = [0.01, 0.03, 0.01, 0.01, 0.01, 0.09]  # the chunks after a terminating one did not run
    assert s["u_mean"] == pytest.approx(np.mean(ran)) and s["u_max"] == pytest.approx(0.09)
    assert s["stopped"] == 2 and s["stopped_at_chunk_mean"] == 0.5
    assert s["u_mean_per_episode"] == pytest.approx([0.02, 0.01, 0.09])
    assert u_summary(result, 2.0, "normalised")["u_max"] == pytest.approx(9.0)  # tau_units picks the array


def test_success_estimate_scores_the_kept_frames_of_objects_the_store_names(tmp_path):
    """The perception scorer on the last context frame and the frames kept before termination (nothing after),
    with the recorded episodes' physics labels beside it; none, with the reason, where it cannot apply."""
    from sc3_jax.core.config import load_config
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.evaluation.diagnose_outcomes import success_rates
    from sc3_jax.evaluation.scorers import RolloutView
    from sc3_jax.benchmarks.bussing.hooks import perception_scorer
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    from sc3_jax.evaluation.rollout_summary import success_estimate

    store = _tiny_store(tmp_path / "eps", n=1, steps=60)
    cfg = load_config("bussing_sim")  # left/right/wrist at 64x64: the scorer's frames
    ep = store.load("ep00")
    frames = np.stack([np.asarray(ep.frames[v])[::2] for v in cfg.data.views])  # [V, T, 64, 64, 3] at 10 Hz
    kept = frames.shape[1] - 2
    garbage = np.full_like(frames[:, :4], 255)  # after termination: must not be read
    imagined = np.concatenate([frames[:, 1:kept + 1], garbage], 1)
    result = {"initial_frames": frames[None, :, :1], "frames": imagined[None],
              "frame_valid": np.r_[np.ones(kept, bool), np.zeros(4, bool)][None]}
    est = success_estimate(result, ["ep00"], store, cfg, perception_scorer)
    objects = tuple(o["name"] for o in ep.meta["labels"]["objects"])
    dests = {o["name"]: o["destination"] for o in ep.meta["labels"]["objects"]}
    want = PerceptionScorer(perception.load()).score(RolloutView("ep00", frames[:, :kept + 1], objects, dests))
    assert est["available"] and est["imagined"] == success_rates([want]) and est["imagined"]["n_objects"] == 3
    read_all = PerceptionScorer(perception.load()).score(RolloutView("ep00", np.concatenate([frames[:, :1], imagined],
                                                                                            1), objects, dests))
    assert success_rates([read_all]) != est["imagined"]  # the frames after termination would change it (a placing)
    assert est["recorded_physics"] == success_rates([ep.meta["labels"]["objects"]])
    # an .npz of conditions
    assert "names no objects" in success_estimate(result, ["ep00"], None, cfg, perception_scorer)["note"]
    small = load_config("tiny")
    assert "64x64" in success_estimate(result, ["ep00"], store, small, perception_scorer)["note"]
