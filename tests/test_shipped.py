"""The shipped world model README command 1 evaluates inside, and the state reader a sweep picks."""
import dataclasses
import hashlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.model import checkpoint
from sc3_jax.rollout import rollout
from sc3_jax.benchmarks.bussing import perception, sweep


def test_command_1s_default_is_the_headline_model_and_loads_with_its_tokenizer_and_state_reader():
    path = sweep.SHIPPED_WORLD_MODEL
    assert sweep.SweepConfig().world_model == str(path)
    cfg, stats, params = checkpoint.load(path)
    assert cfg.name == "bussing_latent_gpu" and cfg.model.tokenizer == "conv_ae"
    # the headline's gripper reader (perception_ft1, git show 2897b53:sc3_jax/benchmarks/bussing/perception.npz)
    reader_path = path / sweep.STATE_READER_FILE
    assert hashlib.sha256(reader_path.read_bytes()).hexdigest().startswith("5d93f49d9337f397")
    reader = perception.state_reader(perception.load(reader_path))
    gap = float(reader.apply(reader.params, jnp.zeros((3, 64, 64, 3), jnp.uint8)))
    assert 0.0 <= gap <= 0.09
    robot = checkpoint.read_robot(path)  # its recorded robot facts: 20 fps, 7-D delta_ee, the three views
    assert (robot.fps, robot.action_space.kind, robot.action_dim, robot.views) == (20.0, "delta_ee", 7,
                                                                                 ("left", "right", "wrist"))
    ro = rollout.Rollout(cfg, stats, data_fps=robot.fps, state_reader=reader)  # loads the shipped tokenizer
    assert ro.spec.views == 3 and tuple(ro.spec.image_size) == (64, 64)
    assert all(np.all(np.isfinite(np.asarray(v, np.float32))) for v in jax.tree_util.tree_leaves(params))


def test_the_state_reader_is_the_given_one_else_the_world_models_own_else_the_scorers(tmp_path):
    wm = tmp_path / "wm"
    wm.mkdir()
    cfg = sweep.SweepConfig(world_model=str(wm))
    assert sweep.default_state_reader(cfg) is None  # no file: the scorer's weights
    (wm / sweep.STATE_READER_FILE).write_bytes(b"x")
    assert sweep.default_state_reader(cfg) == str(wm / sweep.STATE_READER_FILE)
    given = dataclasses.replace(cfg, state_reader="elsewhere.npz")
    assert sweep.default_state_reader(given) == "elsewhere.npz"
    # resolved for a real-only sweep too, so such a store resumes with world-model modes added
    assert sweep.default_state_reader(dataclasses.replace(cfg, modes=("real",))) == str(wm / sweep.STATE_READER_FILE)



def test_the_distilled_student_is_its_teachers_architecture_in_its_units_with_trained_weights():
    """exports/bussing_latent_gpu_student (docs/sweep.md#sampler-steps): the shipped model distilled to 1 step."""
    student = Path(__file__).resolve().parents[1] / "exports" / "bussing_latent_gpu_student"
    cfg, _, params = checkpoint.load(student)
    tcfg, _, tparams = checkpoint.load(sweep.SHIPPED_WORLD_MODEL)
    # the same model, read with its own copy of the teacher's tokenizer
    assert dataclasses.replace(cfg.model, tokenizer_path=tcfg.model.tokenizer_path) == tcfg.model
    assert (student / "norm_stats.json").read_text() == (sweep.SHIPPED_WORLD_MODEL / "norm_stats.json").read_text()
    tok = "tokenizer/ae_params.npz"
    assert (student / tok).read_bytes() == (sweep.SHIPPED_WORLD_MODEL / tok).read_bytes()
    # the teacher as recorded when the student was distilled (before sc3_jax/evaluate/ became evaluation/)
    assert cfg.flow.distill_teacher == "sc3_jax/evaluate/shipped/bussing_latent_gpu" and cfg.flow.distill_steps == 2
    leaves, tleaves = jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(tparams)
    assert all(np.all(np.isfinite(np.asarray(v, np.float32))) for v in leaves)
    assert any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(leaves, tleaves))
    assert (student / sweep.STATE_READER_FILE).read_bytes() == (sweep.SHIPPED_WORLD_MODEL /
                                                                sweep.STATE_READER_FILE).read_bytes()
