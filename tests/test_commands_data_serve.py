"""``sc3 data``, ``sc3 serve-policy``, ``sc3 convert``, ``sc3 demo``: every option's --help text sits under its own
flag, the spellings from before the move still parse, bad input is rc 2 with one line, and each command ends by
saying what it wrote where (the demo: a verdict per check against its baseline)."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import typing

import pytest

from sc3_jax.commands import demo_run as demo_pieces
from sc3_jax.cli import main as sc3
from sc3_jax.commands import convert, data, demo, parse, parse_with_config, serve_policy
from test_commands_help import _help_text, _leaves, _misplaced
from sc3_jax.core.errors import UserError

TARGETS = {"data import-lerobot": data.ImportLerobot, "data export-lerobot": data.ExportLerobot,
           "serve-policy": serve_policy.Args, "convert": convert.Args, "demo": demo.Args}


@pytest.mark.parametrize("where", sorted(TARGETS))
def test_help_gives_every_option_its_own_docstring(where, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    args = TARGETS[where]
    text = _help_text([*where.split(), "--help"], capsys)
    assert args.__doc__.split("\n")[0].strip()[:40] in text
    problems = _misplaced(text, list(_leaves(args)), f"sc3 {where} --help")
    assert not problems, "\n".join(problems)


def test_data_lists_its_subcommands_and_refuses_others(capsys):
    assert data.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name, args in data.SUBCOMMANDS.items():
        assert re.search(rf"^\s+{re.escape(name)}\s+{re.escape(args.__doc__.strip().splitlines()[0])}$", out, re.M)
    for argv in ([], ["import"], ["--out", "x"]):
        assert data.main(argv) == 2
        err = capsys.readouterr().err
        assert "sc3 data: error" in err and all(f"  {name} " in err for name in data.SUBCOMMANDS)


@pytest.mark.parametrize("where, argv, expected", [
    ("data import-lerobot", ["--data", "root", "--out", "o", "--views", "left=cam_high", "wrist", "--wrist", "wrist",
                             "--fps", "10", "--image-size", "48", "64", "--action-key", "act", "--pose-key", "pose",
                             "--allow-missing-pose"],
     dict(data="root", out="o", views=("left=cam_high", "wrist"), wrist=("wrist",), fps=10.0, image_size=(48, 64),
          action_key="act", pose_key="pose", allow_missing_pose=True, action_space=None, action_names=None,
          action_targets=None, state_key="auto", episodes=None, id_prefix="")),
    ("data import-lerobot", ["--data", "root", "--out", "o"],
     dict(data="root", out="o", views=None, wrist=None, fps=None, image_size=None, action_key="action",
          pose_key="observation.state", allow_missing_pose=False, action_space=None, action_names=None,
          action_targets=None, state_key="auto", episodes=None, id_prefix="")),
    ("data export-lerobot", ["--data", "s", "--out", "o", "--version", "v2.1", "--codec", "av1", "--crf", "30", "--images",
                             "image", "--views", "left", "right", "--overwrite"],
     dict(data="s", out="o", version="v2.1", codec="av1", crf=30, images="image", views=("left", "right"),
          overwrite=True)),
    ("data export-lerobot", ["--data", "s", "--out", "o"],
     dict(data="s", out="o", version="v3.0", codec="h264", crf=None, images="video", views=None, overwrite=False)),
    ("serve-policy", ["--policy", "zero", "--host", "127.0.0.1", "--port", "0", "--family", "libero",
                      "--image-size", "48", "64", "--num-views", "2", "--task-prompt", "3=wipe it", "--task-prompt",
                      "4=stack", "--default-task", "1", "--api-key-file", "k", "--max-message-mb", "2", "--log-level",
                      "warning", "--benchmark", "bussing"],
     dict(policy="zero", host="127.0.0.1", port=0, family="libero", image_size=(48, 64), num_views=2,
          task_prompt=("3=wipe it", "4=stack"), default_task=1, benchmark="bussing", api_key_file="k",
          max_message_mb=2.0, log_level="warning")),
    ("serve-policy", ["--policy", "zero"],
     dict(policy="zero", host="127.0.0.1", port=8000, family="native", image_size=None, num_views=None,
          task_prompt=(), default_task=None, benchmark="none", api_key_file=None, max_message_mb=8.0,
          log_level="INFO")),
    ("convert", ["--from", "diffusers", "src", "--to", "out", "--dtype", "bfloat16"],
     dict(src_kind="diffusers", src="src", to="out", dtype="bfloat16")),
    ("convert", ["src", "--from", "sc3", "--to", "out"], dict(src_kind="sc3", src="src", to="out", dtype="float32")),
    ("demo", ["--out", "o", "--config", "small", "--steps", "5", "--episodes", "3", "--batch", "4"],
     dict(out="o", config="small", steps=5, episodes=3, batch=4)),
    ("demo", [], dict(out="runs/demo", config="tiny", steps=None, episodes=200, batch=None)),
])
def test_the_spellings_from_before_still_parse(where, argv, expected):
    assert dataclasses.asdict(parse(TARGETS[where], argv, where)) == expected


def test_choices_are_the_librarys():
    """The choices spelled out in the Args (so that --help loads no library) are the library's own."""
    from sc3_jax.commands.convert_cli import DTYPES
    from sc3_jax.policies.openpi_mappings import PRESETS

    def choices(args, field):
        return typing.get_args(typing.get_type_hints(args)[field])

    assert choices(serve_policy.Args, "family") == ("native", *PRESETS)
    assert choices(convert.Args, "dtype") == DTYPES


def test_demo_takes_config_overrides_over_its_own_paths(tmp_path):
    a, cfg = parse_with_config(demo.Args, ["--out", str(tmp_path), "--steps", "7", "--batch", "4"], "demo",
                               demo._config)
    assert (cfg.data.path, cfg.train.workdir) == (str(tmp_path / "episodes"), str(tmp_path / "train"))
    assert (cfg.train.steps, cfg.data.batch_size, a.episodes) == (7, 4, 200)


@pytest.mark.parametrize("argv", [
    ["data", "import-lerobot", "--data", "{tmp}/none", "--out", "{tmp}/o"],  # not a LeRobot dataset
    ["data", "export-lerobot", "--data", "{tmp}/none", "--out", "{tmp}/o"],  # not an episode store
    ["convert", "--from", "sc3", "{tmp}/none", "--to", "{tmp}/o"],  # no model there
    ["serve-policy", "--policy", "zero", "--log-level", "LOUD", "--port", "0"],
    ["serve-policy", "--policy", "zero", "--family", "libero", "--task-prompt", "wipe it", "--port", "0"],
    ["serve-policy", "--policy", "no_such_policy", "--port", "0"],
    ["serve-policy", "--policy", "zero", "--family", "droid", "--port", "0"],  # 7-D actions, DROID's are 8-D
    ["demo", "--stepz", "3"],  # an option it does not take: the one it meant, in one line
])
def test_bad_input_is_rc_2_with_one_line(argv, tmp_path, capsys):
    assert sc3([x.format(tmp=tmp_path) for x in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"sc3 {argv[0]}: error: ") and "\n" not in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv", [["data", "export-lerobot", "--data", "s", "--out", "o", "--codec", "vp9"],
                                  ["convert", "--from", "torch", "s", "--to", "o"], ["convert", "s"],
                                  ["serve-policy"]])
def test_usage_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as e:
        sc3(argv)
    assert e.value.code == 2 and capsys.readouterr().err


def test_export_then_import_say_what_they_wrote(tmp_path, capsys):
    pytest.importorskip("pyarrow")
    pytest.importorskip("av")
    from sc3_jax.data import synthetic
    from sc3_jax.data.episodes import EpisodeStore

    src = synthetic.generate(tmp_path / "s", 2, length=12, image_size=(16, 16), progress=False)
    frames = sum(src.load(e).length for e in src.episode_ids())
    assert data.main(["export-lerobot", "--data", str(tmp_path / "s"), "--out", str(tmp_path / "lr"), "--views", "left",
                      "wrist"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert out.startswith(f"exported 2 episodes, {frames} frames") and str(tmp_path / "lr") in out
    assert f"views left, wrist as observation.images.VIEW, actions (delta_ee {src.action_dim}-D) as action" in out

    assert data.main(["import-lerobot", "--data", str(tmp_path / "lr"), "--out", str(tmp_path / "back"), "--views",
                      "l=observation.images.left", "wrist"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    back = EpisodeStore(tmp_path / "back")
    assert back.views == ["l", "wrist"] and len(back) == 2
    assert lines[-2] == (f"imported 2 episodes (0 already there) from {tmp_path / 'lr'}; {tmp_path / 'back'} now "
                         f"holds 2 episodes, {frames} frames of views l, wrist at {src.fps} fps, 16x16, actions delta_ee "
                         f"{back.action_dim}-D")
    assert lines[-1] == f"train on it: sc3 train --config NAME --data {tmp_path / 'back'}"


def test_serve_policy_prints_its_address_and_metadata(monkeypatch, capsys):
    from sc3_jax.policies import openpi_server

    served = []

    def serve_once(server):  # what Ctrl-C at once would do: shut down, having bound the port
        served.append(server)
        server.shutdown()
        return server

    monkeypatch.setattr(openpi_server, "serve_until_interrupted", serve_once)
    assert serve_policy.main(["--policy", "zero", "--host", "127.0.0.1", "--port", "0", "--family", "libero",
                              "--log-level", "WARNING"]) == 0
    (server,) = served
    out = capsys.readouterr().out
    assert server.port > 0 and f"serving zero on ws://127.0.0.1:{server.port} (family libero)" in out
    assert f"http://127.0.0.1:{server.port}/healthz" in out
    meta = json.loads(re.search(r"metadata sent to every client: (\{.*\})", out).group(1))
    assert meta == server.metadata and meta["policy"] == "zero" and meta["action_dim"] == 7


def test_serve_policy_takes_a_benchmarks_prompts_and_policy_names_only_when_named():
    from sc3_jax.benchmarks.bussing.tasks import PROMPTS
    from sc3_jax.benchmarks.bussing.zoo import zoo_names

    argv = ["--policy", "zero", "--host", "127.0.0.1", "--port", "0", "--family", "libero"]
    plain = serve_policy.build_server(parse(serve_policy.Args, argv, "serve-policy"))
    bussing = serve_policy.build_server(parse(serve_policy.Args, argv + ["--benchmark", "bussing"], "serve-policy"))
    try:  # without --benchmark the table is empty: any prompt is task 0, no benchmark's words are assumed
        assert plain.mapping.prompts is None and int(plain.mapping.task_for("wipe it")) == 0
        assert dict(bussing.mapping.prompts) == PROMPTS
    finally:
        plain.shutdown()
        bussing.shutdown()
    zoo = zoo_names("bussing")[0]
    with pytest.raises(UserError, match=f"--policy {zoo}"):  # a zoo name is the benchmark's, not the core's
        serve_policy.build_server(parse(serve_policy.Args, ["--policy", zoo, "--port", "0"], "serve-policy"))


def test_convert_says_what_it_passed_and_wrote(tmp_path, monkeypatch, capsys):
    """The command passes its options through and reports the library's answer (the real conversions:
    test_convert_round_trip_says_what_it_wrote, and tests/test_cosmos3.py)."""
    from sc3_jax.commands import convert_cli

    calls = []

    def fake(src, out, dtype):
        calls.append((src, out, dtype))
        return convert_cli.Converted(tmp_path / "o", ("config.json", "params/"), 1_234_567, dtype)

    monkeypatch.setattr(convert_cli, "from_diffusers", fake)
    assert convert.main(["--from", "diffusers", "in", "--to", "o", "--dtype", "bfloat16"]) == 0
    out = capsys.readouterr().out
    assert calls == [("in", "o", "bfloat16")]
    assert f"wrote {tmp_path / 'o'} (config.json, params/): 1.23M parameters as bfloat16, from diffusers in" in out
    assert f"--train.init-from {tmp_path / 'o'}" in out


def test_convert_round_trip_says_what_it_wrote(tmp_path, capsys):
    pytest.importorskip("safetensors")
    import jax

    from sc3_jax.model import checkpoint
    from sc3_jax.core.config import Config
    from sc3_jax.model import convert as mconvert
    from sc3_jax.model import dit

    cfg = mconvert.config_from_diffusers({"_class_name": "Cosmos3OmniTransformer", "hidden_size": 64,
                                          "num_hidden_layers": 1, "num_attention_heads": 4, "num_key_value_heads": 2,
                                          "head_dim": 32, "intermediate_size": 96, "rope_axes_dim": [6, 5, 5],
                                          "latent_channel": 4, "latent_patch_size": 2, "patch_latent_dim": 16,
                                          "action_gen": True, "action_dim": 8, "num_embodiment_domains": 3,
                                          "vocab_size": 50})
    params = dit.init_params(cfg, mconvert.token_dim(cfg), jax.random.key(0))
    n = dit.count_params(params)
    checkpoint.save_converted(tmp_path / "ours", Config(model=cfg), params)
    assert convert.main(["--from", "sc3", str(tmp_path / "ours"), "--to", str(tmp_path / "hf")]) == 0
    assert convert.main(["--from", "diffusers", str(tmp_path / "hf"), "--to", str(tmp_path / "back")]) == 0
    lines = capsys.readouterr().out.splitlines()
    files = sorted(p.name for p in (tmp_path / "hf").iterdir())
    assert lines[0] == (f"wrote {tmp_path / 'hf'} ({', '.join(files)}): {n / 1e6:.2f}M parameters as float32, from "
                        f"sc3 {tmp_path / 'ours'}")
    assert lines[2].startswith(f"wrote {tmp_path / 'back'} (config.json, params/): {n / 1e6:.2f}M parameters")


METRICS = dict(fd_psnr=24.1, copy_last_psnr=21.0, fd_shuffled_psnr=23.9, id_mse=0.5, id_sample_mse=0.6,
               mean_action_mse=1.0, cvi_psnr=20.0, mean_frame_psnr=17.0)


def test_demo_verdicts_against_the_baselines():
    got = {v.check: v.passed for v in demo_pieces.verdicts(METRICS)}
    # 24.1 beats 21.0 by more than 0.5 dB; 23.9 is within 0.5 dB; 0.5 < 0.7 x 1.0; 20.0 beats 17.0 by more than 1 dB
    assert got == {"forward dynamics": True, "uses its actions": False, "inverse dynamics": True, "inpainting": True}
    assert not any(v.passed for v in demo_pieces.verdicts({k: math.nan for k in METRICS}))
    assert demo_pieces.verdicts(METRICS)[0].line() == \
        "forward dynamics : PSNR 24.10 dB vs repeat-last-frame 21.00 dB (needs +0.5 dB): PASS"


def test_demo_ends_with_a_verdict_per_check_and_where_its_outputs_are(tmp_path, monkeypatch, capsys):
    """The steps are stubbed (the real run: tests/test_learning.py, ~10 min): what the demo says about them."""
    from sc3_jax.data import synthetic
    from sc3_jax.data.episodes import EpisodeStore

    made, trained = [], []
    def generate(path, n, **kw):  # an empty store: the demo reads its frame rate and state size into the model
        made.append((path, n))
        EpisodeStore(path, views=["cam"], fps=20, image_size=(8, 8), create=True)

    monkeypatch.setattr(synthetic, "generate", generate)
    monkeypatch.setattr(demo_pieces, "train_and_evaluate", lambda cfg, heldout: trained.append(cfg) or METRICS)
    assert demo.main(["--out", str(tmp_path), "--steps", "3", "--episodes", "5"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert made == [(str(tmp_path / "episodes"), 5), (str(tmp_path / "heldout"), 16)]
    assert trained[0].train.steps == 3 and trained[0].train.workdir == str(tmp_path / "train")
    assert json.loads((tmp_path / "demo_metrics.json").read_text()) == METRICS
    assert [line for line in out if line.endswith(("PASS", "FAIL"))] == [
        v.line() for v in demo_pieces.verdicts(METRICS)]
    assert out[-2].startswith("3/4 checks pass")
    assert out[-1] == (f"outputs: metrics {tmp_path / 'demo_metrics.json'}, checkpoints {tmp_path / 'train'}, "
                       f"episodes {tmp_path / 'episodes'} and {tmp_path / 'heldout'}")
