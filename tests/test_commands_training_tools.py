"""``sc3 plan``, ``sc3 train-tokenizer`` and ``sc3 train-perception``: every option's help under its own flag, the
documented command lines parse (an option a command does not take is refused, naming the closest), overrides reach
the config, bad input is one line with exit status 2, and each command's closing summary says what its numbers
are measured against. Cheap: nothing here trains or lowers a model."""
from __future__ import annotations

import dataclasses

import pytest
from test_commands_help import _help_text, _leaves, _misplaced

from sc3_jax import cli
from sc3_jax.cli import main
from sc3_jax.commands import parse
from sc3_jax.benchmarks.bussing.commands import train_perception
from sc3_jax.commands import plan as plan_command
from sc3_jax.commands import train_tokenizer

MODULES = {"plan": plan_command, "train-tokenizer": train_tokenizer, "train-perception": train_perception}


@pytest.fixture(autouse=True)
def _commands(monkeypatch):
    """Dispatch all three through `sc3` (cli.MODULES may not list train-perception yet)."""
    for name, module in MODULES.items():
        monkeypatch.setitem(cli.COMMANDS, name, module.main)


def _rc(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as e:  # tyro's usage error
        return e.code


@pytest.mark.parametrize("command", sorted(MODULES))
def test_help_gives_every_option_its_own_docstring(command, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    args = MODULES[command].Args
    text = _help_text([command, "--help"], capsys)
    assert args.__doc__.split()[0] in text
    leaves = list(_leaves(args))
    assert len(leaves) == len({flag for _, _, flag in leaves}) > 5
    problems = _misplaced(text, leaves, f"sc3 {command} --help")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("command, argv, expected", [
    ("plan", ["--config", "paper", "--mesh", "data=4,fsdp=8", "--device", "gb200", "--mfu", "0.3", "--compile",
              "--no-chunk"],
     dict(config="paper", mesh="data=4,fsdp=8", device="gb200", mfu=0.3, compile=True, chunk=False)),
    ("plan", [], dict(config="tiny", mesh="data=1", device="h100", mfu=0.4, compile=False, chunk=True)),
    # scripts/world_model.sh
    ("train-tokenizer", ["--data", "D", "--heldout", "H", "--workdir", "W", "--steps", "2200", "--ae.width", "96",
                         "--ae.mid-width", "48", "--ae.out-width", "24", "--ae.blocks", "1", "--ae.latent-channels",
                         "16", "--views", "left", "wrist", "--no-progress", "--export-only"],
     dict(data="D", heldout="H", workdir="W", steps=2200, views=("left", "wrist"), progress=False, export_only=True,
          ae=dict(latent_channels=16, downsample=4, width=96, mid_width=48, out_width=24, blocks=1))),
    # docs/sweep.md
    ("train-perception", ["--data", "a", "b", "c", "--keypoints", "64", "--widths", "32", "64", "64", "--hidden",
                          "384", "--pos-weight", "2", "--steps", "3000", "--lr", "1e-3", "--out", "o.npz"],
     dict(data=("a", "b", "c"), keypoints=64, widths=(32, 64, 64), hidden=384, pos_weight=2.0, steps=3000,
          lr=1e-3, out="o.npz", validate=())),
    ("train-perception", ["--data", "a", "b", "--generate-policies", "208", "--policy-seed", "70", "--init", "w.npz",
                          "--generate", "300", "--max-episodes", "9", "--stride", "3", "--batch", "32", "--seed", "1"],
     dict(data=("a", "b"), generate_policies=208, policy_seed=70, init="w.npz", generate=300, max_episodes=9,
          stride=3, batch=32, seed=1)),
    ("train-perception", ["--validate", "r1", "r2", "--init", "w.npz"], dict(validate=("r1", "r2"), init="w.npz")),
])
def test_the_documented_command_lines_parse(command, argv, expected):
    got = dataclasses.asdict(parse(MODULES[command].Args, argv, command))
    assert {k: got[k] for k in expected} == expected


def test_plan_config_overrides_reach_the_config(monkeypatch, capsys):
    seen = {}

    def fake_plan(cfg, mesh_cfg, device, mfu, compile, chunk, *, action_space, data_fps):
        seen.update(cfg=cfg, mesh=mesh_cfg, device=device, chunk=chunk, robot=(action_space, data_fps))
        return {}

    from sc3_jax.train import plan
    from sc3_jax.core.config import MeshConfig
    monkeypatch.setattr(plan, "plan", fake_plan)
    monkeypatch.setattr(plan, "format_plan", lambda p: "verdict: stub")
    assert main(["plan", "--config", "tiny", "--mesh", "data=2,fsdp=4", "--batch", "64",
                 "--model.attention-impl", "blockwise", "--device", "v5p", "--no-chunk"]) == 0
    cfg = seen["cfg"]
    assert (cfg.name, cfg.data.batch_size, cfg.model.attention_impl) == ("tiny", 64, "blockwise")
    assert seen["mesh"] == MeshConfig(2, 4, 1, 1) and seen["device"] == "v5p" and seen["chunk"] is False
    assert seen["robot"] == (None, None)  # no --data: no robot facts assumed (shape_check.cost_robot's stand-ins)
    assert capsys.readouterr().out.strip() == "verdict: stub"


def test_plan_help_config_lists_the_config_fields(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    text = _help_text(["plan", "--config", "tiny", "--help-config"], capsys)
    assert "--model.attention-impl" in text and "--data.batch-size" in text  # listed; given, it is refused for --batch


@pytest.mark.parametrize("argv, message", [
    (["plan", "--set", "data.batch_size=64"], "unknown option --set"),
    (["plan", "--model.attention-imp", "ring"], "--model.attention-imp (did you mean --model.attention-impl?"),
    (["plan", "--mesh.context", "4"], "--mesh AXIS=SIZE"),
    (["plan", "--mesh", "pipeline=2"], "--mesh: expected AXIS=SIZE"),
    (["plan", "--config", "no_such_config"], "no config 'no_such_config'"),
    (["plan", "--mesh", "data=3"], "global batch 32 does not divide over data x fsdp = 3"),
    (["plan", "--mfu", "2"], "--mfu must be in (0, 1]"),
    (["train-perception"], "--data"),
    (["train-perception", "--data", "a", "--generate", "5"], "at least two"),
])
def test_bad_input_is_one_line_and_status_2(argv, message, capsys):
    assert _rc(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"sc3 {argv[0]}: error: ") and message in err


def test_an_architecture_the_autoencoder_cannot_build_is_a_usage_error(capsys):
    assert _rc(["train-tokenizer", "--ae.downsample", "3"]) == 2  # tyro's usage error, naming the value
    assert "power of two" in capsys.readouterr().err


def test_plan_refuses_a_device_it_does_not_know(capsys):
    assert _rc(["plan", "--device", "tpu"]) == 2 and "tpu" in capsys.readouterr().err


def test_train_tokenizer_without_data_says_so_and_creates_nothing(tmp_path, capsys):
    """No store is a default (it named the bussing benchmark's demos): --data is asked for in one line."""
    assert _rc(["train-tokenizer", "--workdir", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--data: give the episode store" in err and not (tmp_path / "w").exists()


def test_export_only_without_a_checkpoint_says_so_and_creates_nothing(tmp_path, capsys):
    assert _rc(["train-tokenizer", "--export-only", "--workdir", str(tmp_path / "w")]) == 2
    assert "no checkpoint to export" in capsys.readouterr().err and not (tmp_path / "w").exists()


def test_tokenizer_command_help_loads_no_jax():
    """The options live in tokenizer_config.py (one home, no jax), so --help stays fast."""
    import subprocess
    import sys
    code = ("import sys; from sc3_jax.commands import train_tokenizer; "
            "sys.exit(1 if 'jax' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_tokenizer_summary_puts_each_psnr_beside_its_baseline():
    cfg = train_tokenizer.Args(workdir="W", heldout="H", eval_frames=8)
    view = dict(psnr=31.04, static_psnr=22.96, psnr_moving=26.51, static_psnr_moving=12.04, moving_fraction=0.055)
    lines = train_tokenizer.summary(cfg, {"params": 740_000, "latent": [16, 16, 16], "heldout": {"left": view}})
    assert lines[0].startswith("tokenizer: W/tokenizer (0.74M parameters; latents 16x16x16")
    assert "W/tokenizer/eval.json" in "\n".join(lines) and "temporal median" in "\n".join(lines)
    assert lines[-1] == "| left | 31.0 | 23.0 | 26.5 | 12.0 | 5.5% |"
    bare = train_tokenizer.summary(dataclasses.replace(cfg, heldout=None), {"params": 1, "latent": [1, 1, 1]})
    assert "--heldout" in bare[-1]


def test_perception_training_summary_gives_each_head_and_the_always_no_baseline():
    m = {"steps": 10, "train_frames": 900, "seconds": 3.0, "heldout_frames": 100, "heldout_width_mae_m": 0.0012}
    for name, (acc, pos, prec, rec) in {"lifted": (0.95, 0.10, 0.8, 0.7), "in_bin": (0.97, 0.08, 0.9, 0.85)}.items():
        m |= {f"heldout_acc/{name}": acc, f"heldout_positive/{name}": pos, f"heldout_precision/{name}": prec,
              f"heldout_recall/{name}": rec}
    lines = train_perception.training_summary("o.npz", m, ("lifted", "in_bin"))
    assert lines[0].startswith("weights: o.npz (10 steps on 900 frames")
    assert "| lifted | 0.950 | 0.900 | 0.800 | 0.700 |" in lines
    assert "| in_bin | 0.970 | 0.920 | 0.900 | 0.850 |" in lines
    assert "1.2 mm" in "\n".join(lines) and "--validate RESULTS --init o.npz" in lines[-1]


def test_majority_guess_and_validation_summary():
    from sc3_jax.benchmarks.bussing.perception_train import majority_agreement
    from sc3_jax.evaluation.scorers import agreement

    def obj(language, lifting, placing, outcome):
        return dict(language=language, lifting=lifting, placing=placing, outcome=outcome)

    truth = [[obj(True, True, False, "placing"), obj(True, False, False, "lifting")],
             [obj(True, True, True, "no_failure"), obj(False, True, False, "language")]]
    floor = majority_agreement(truth)
    assert floor == dict(language=0.75, lifting=0.75, placing=0.75, outcome=0.25, n_objects=4)
    got = {"clean": agreement(truth, truth), "majority_guess": floor}
    lines = train_perception.validation_summary("w.npz", "R", got)
    assert "(4 objects)" in lines[0] and lines[1] == "| frames | language | lifting | placing | outcome |"
    assert lines[3] == "| clean | 1.000 | 1.000 | 1.000 | 1.000 |"
    assert lines[4] == "| majority guess (floor) | 0.750 | 0.750 | 0.750 | 0.250 |"


@pytest.mark.parametrize("fits, fit, expected", [
    (True, None, "verdict: fits on 8 x h100: 50.00 GB per device of a 72 GB budget (90% of HBM)"),
    (False, {"attention_impl": "fused", "remat": "dots", "microbatches": 4},
     "verdict: does not fit on 8 x h100: 100.00 GB per device > 72 GB (90% of HBM), activations 85.00 GB of it; it "
     "fits with --model.attention-impl fused --model.remat dots --train.grad-accum 4"),
    (False, None, "no attention kernel, remat or micro-batching fits: split the sequence (--mesh ...,context=N "
                  "--model.attention-impl ring)"),
])
def test_plan_verdict_says_whether_it_fits_and_why(fits, fit, expected):
    from sc3_jax.train.plan import verdict

    total = 50e9 if fits else 100e9
    p = dict(fits=fits, fit=fit, hbm_bytes=80e9, devices=8, device="h100", mfu=0.4, total_bytes=total,
             params_bytes=5e9, optimizer_bytes=5e9, grads_bytes=5e9, other_bytes=0.0, activations_bytes=total - 15e9)
    assert expected in verdict(p)
