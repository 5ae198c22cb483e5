"""Every world model the project ships (``sc3_jax/benchmarks/bussing/shipped/``) or exports (``exports/``) is usable as
it is committed: its robot facts read (checkpoint.read_robot, what `sc3 rollout` and `sc3 sweep` read) and, in the slow
variant, a chunk rolls out inside it the way the sweeps build their rollout. A model made by `sc3 demo` records its
data's facts; a model's facts never come from the current directory, and a damaged fact is one line."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from sc3_jax.model import checkpoint
from sc3_jax.core.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
MODELS = sorted([*(ROOT / "exports").iterdir(), *(ROOT / "sc3_jax" / "benchmarks" / "bussing" / "shipped").iterdir()])
MODELS = [p for p in MODELS if (p / "config.json").is_file()]
STUDENT = ROOT / "exports" / "bussing_latent_gpu_student"
# the robots they were trained on (docs/world_model.md, docs/so101.md): bussing's simulator records 20 fps and no
# state; the SO-101 simulator 10 fps and a 14-D state
FPS = {"bussing": 20.0, "so101": 10.0}
STATE_DIM = {"bussing": 0, "so101": 14}


def _robot_of(path: Path) -> str:
    return "so101" if path.name.startswith("so101") else "bussing"


def test_the_models_are_the_ones_the_docs_name():
    names = {p.name for p in MODELS}
    assert {"bussing_latent_gpu", "bussing_sim", "bussing_latent_cpu", "bussing_latent_gpu_student",
            "so101_latent_cpu", "so101_v2_cpu", "so101_v3_cpu"} <= names


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_every_shipped_and_exported_model_reads_its_robot_facts_from_its_own_directory(path, tmp_path, monkeypatch):
    from sc3_jax.rollout import rollout, state_head
    from sc3_jax.evaluation.engine import mesh_for as _mesh

    monkeypatch.chdir(tmp_path)  # nothing of the current directory is read (an empty one here)
    cfg = checkpoint.read_config(path)
    robot = checkpoint.read_robot(path, cfg)
    kind = _robot_of(path)
    assert (robot.fps, robot.state_dim) == (FPS[kind], STATE_DIM[kind])
    assert robot.action_dim == cfg.model.action_dim and len(set(robot.views)) == len(robot.views) == cfg.model.num_views
    # the rollout `sc3 sweep episodes` builds (evaluation/ic_sweep.py), learned state included: its shapes check out
    head = state_head.load(path)
    ro = rollout.Rollout(cfg, checkpoint.read_norm_stats(path), mesh=_mesh(1), data_fps=robot.fps, head=head)
    assert ro.spec.stride == round(robot.fps / cfg.rollout.control_hz) >= 1
    assert ro.spec.state_dim == state_head.state_dim(head)


def test_the_students_documented_sweep_reads_its_facts_and_samples_in_its_one_step():
    """docs/results.md: ``sc3 sweep bench --world-model exports/bussing_latent_gpu_student --sample-steps 1``: the
    bussing sweep's loading path up to its rollout spec (benchmarks/bussing/sweep.py run_sweep), no warning."""
    import warnings

    from sc3_jax.rollout import rollout
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig
    from sc3_jax.evaluation.world_model_defaults import evaluation_config, warn_if_student_off_its_step

    assert "--world-model exports/bussing_latent_gpu_student --sample-steps 1" in (ROOT / "docs/results.md").read_text()
    cfg = SweepConfig(world_model=str(STUDENT), sample_steps=1)
    wcfg = evaluation_config(checkpoint.read_config(cfg.world_model), cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_student_off_its_step(wcfg)
    robot = checkpoint.read_robot(cfg.world_model, wcfg)
    spec = rollout.make_spec(wcfg, robot.fps, action_space=robot.action_space)
    assert (spec.stride, spec.steps, tuple(spec.image_size)) == (2, 1, (64, 64))


class Still:
    """A host policy commanding zeros, whatever robot state it is handed (the learned one where the model has it)."""

    def __init__(self, chunk: int, action_dim: int, state_dim: int):
        self.chunk, self.action_dim, self.state_dim = chunk, action_dim, state_dim

    def infer(self, obs):
        assert np.asarray(obs["state"]).shape[-1] == self.state_dim
        return np.zeros((self.chunk, self.action_dim), np.float32)


def _one_chunk(path: Path, sample_steps: int | None = None) -> dict:
    """One chunk of the zero policy inside the model at ``path``, built as `sc3 sweep episodes` builds it."""
    from sc3_jax.rollout import rollout, rollout_io, state_head
    from sc3_jax.evaluation.engine import mesh_for as _mesh
    from sc3_jax.evaluation.world_model_defaults import Sampler, evaluation_config

    wcfg, stats, params = checkpoint.load(path)
    wcfg = evaluation_config(wcfg, Sampler(sample_steps=sample_steps or 1, inverse_steps=1))
    robot = checkpoint.read_robot(path, wcfg)
    head = state_head.load(path)
    ro = rollout.Rollout(wcfg, stats, mesh=_mesh(1), data_fps=robot.fps, num_chunks=1, head=head)
    s = ro.spec
    h, w = s.image_size
    ics = rollout.InitialConditions(np.full((1, s.views, s.context, h, w, 3), 128, np.uint8),
                                    np.zeros((1, s.action_dim), np.float32), np.zeros(1, np.int32),
                                    np.zeros((1, s.state_dim), np.float32) if s.state_dim else None)
    policy = Still(wcfg.rollout.policy_chunk, s.action_dim, s.state_dim or s.action_dim)
    ro.check_policy(policy)
    return rollout_io.closed_loop(ro, params, policy, ics, np.asarray(rollout.episode_keys(0, 1)), math.inf, 1,
                                  False), s


@pytest.mark.slow
@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_a_chunk_rolls_out_inside_every_shipped_and_exported_model(path):
    out, s = _one_chunk(path, 1 if path == STUDENT else None)
    frames = np.asarray(out["frames"])
    assert frames.shape[:3] == (1, s.views, s.keep) and frames.dtype == np.uint8
    assert np.isfinite(np.asarray(out["u_raw"])).all()


# -- a model's facts: its own, or one line --------------------------------------------------------------------
def _copy(tmp_path: Path, src: Path = ROOT / "exports" / "so101_v3_cpu") -> Path:
    dst = tmp_path / "model"
    shutil.copytree(src, dst)
    return dst


def _edit(model: Path, **data) -> None:
    raw = json.loads((model / "config.json").read_text())
    for k, v in data.items():
        if v is None:
            raw["data"].pop(k, None)
        else:
            raw["data"][k] = v
    (model / "config.json").write_text(json.dumps(raw))


def test_a_relative_training_data_path_is_never_read_against_the_current_directory(tmp_path, monkeypatch):
    model = _copy(tmp_path)
    _edit(model, fps=None, state_dim=None, path="train")
    (tmp_path / "cwd" / "train").mkdir(parents=True)  # another store's facts, where the cwd would find them
    (tmp_path / "cwd" / "train" / "dataset.json").write_text(json.dumps({"fps": 30, "state": {"dim": 3}}))
    monkeypatch.chdir(tmp_path / "cwd")
    with pytest.raises(UserError, match=r"no data\.fps .* path 'train' is relative .* add \"fps\": N") as e:
        checkpoint.read_robot(model)
    assert len(str(e.value).splitlines()) == 1
    # the same store named absolutely is read (a workdir on the machine it was trained on)
    _edit(model, path=str(tmp_path / "cwd" / "train"))
    robot = checkpoint.read_robot(model)
    assert (robot.fps, robot.state_dim) == (30.0, 3)


def test_a_frame_rate_the_control_rate_does_not_divide_is_one_line(tmp_path):
    model = _copy(tmp_path)
    _edit(model, fps=15.0)  # control_hz 10: a stride of 1.5 frames
    with pytest.raises(UserError, match=r"data\.fps 15 is not a whole multiple of rollout\.control_hz 10") as e:
        checkpoint.read_robot(model)
    assert len(str(e.value).splitlines()) == 1
    _edit(model, fps=5.0)  # slower than the rollout: a stride below one frame
    with pytest.raises(UserError, match="not a whole multiple"):
        checkpoint.read_robot(model)
    _edit(model, fps=30.0)
    assert checkpoint.read_robot(model).fps == 30.0


def test_a_view_named_twice_is_one_line(tmp_path):
    model = _copy(tmp_path)
    _edit(model, views=["wrist", "wrist"])
    with pytest.raises(UserError, match=r"data\.views \['wrist', 'wrist'\] names 'wrist' twice") as e:
        checkpoint.read_robot(model)
    assert len(str(e.value).splitlines()) == 1


def test_sc3_demo_records_its_datas_frame_rate_in_the_model_it_makes(tmp_path):
    from sc3_jax.commands import demo_run as demo
    from sc3_jax.commands.demo import Args, _config
    from sc3_jax.data import synthetic

    cfg = _config(Args(out=str(tmp_path / "demo"), steps=2))
    assert cfg.data.fps is None  # the config states none: the demo's data does
    synthetic.generate(cfg.data.path, 1, length=8, image_size=cfg.data.image_size, seed=0)
    filled = demo.with_data_facts(cfg)
    info = json.loads((Path(cfg.data.path) / "dataset.json").read_text())
    assert (filled.data.fps, filled.data.state_dim) == (float(info["fps"]), 0)
    # a demo workdir started before demos recorded it resumes as saved (a changed config would be refused)
    Path(cfg.train.workdir).mkdir(parents=True)
    (Path(cfg.train.workdir) / "config.json").write_text(json.dumps({"data": {"fps": None}}))
    assert demo.with_data_facts(cfg).data.fps is None


def test_a_measured_entry_past_the_recorded_state_is_one_line(tmp_path):
    """norm_stats.json's action_space.measured names the recorded-state entries the commands move (SO-101: 11-13 of
    14); one past the state was read without a word, to fail (or read another entry) inside a rollout."""
    model = _copy(tmp_path)
    raw = json.loads((model / "norm_stats.json").read_text())
    raw["action_space"]["measured"] = [11, 12, 20, -1]
    (model / "norm_stats.json").write_text(json.dumps(raw))
    with pytest.raises(UserError, match=r"measured \[11, 12, 20, -1\] names state entries past the recorded "
                                        r"state's 14") as e:
        checkpoint.read_robot(model)
    assert len(str(e.value).splitlines()) == 1


def test_a_policy_of_the_commands_own_state_is_told_the_flag_that_hands_it_that_state():
    """`--policy zero` on an SO-101 model (a 14-D learned state) was refused naming both sizes and not the way out:
    --no-learned-state hands the policy the integrated commands, the state it reads."""
    from sc3_jax.rollout import rollout, state_head
    from sc3_jax.evaluation.engine import mesh_for as _mesh
    from sc3_jax.policies import simple

    path = ROOT / "exports" / "so101_v3_cpu"
    cfg = checkpoint.read_config(path)
    stats = checkpoint.read_norm_stats(path)
    robot = checkpoint.read_robot(path, cfg)
    ro = rollout.Rollout(cfg, stats, mesh=_mesh(1), data_fps=robot.fps, head=state_head.load(path))
    zero = simple.builtin("zero", cfg.rollout.policy_chunk, stats.action_space, len(cfg.data.views))
    with pytest.raises(UserError, match=r"has 14-D states: --no-learned-state hands it the integrated commands "
                                        r"\(4-D\) instead$"):
        ro.check_policy(zero)
    rollout.Rollout(cfg, stats, mesh=_mesh(1), data_fps=robot.fps, head=None).check_policy(zero)  # what it says
