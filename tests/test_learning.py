"""Learning is real: the tiny config trained for a few CPU-minutes on the synthetic environment beats the baseline
each capability must beat, on held-out episodes (sc3_jax/evaluate/world_model.py)."""
import pytest

from sc3_jax.config import load_config, replace
from sc3_jax.data import synthetic
from sc3_jax.demo import train_and_evaluate

STEPS = 1200


@pytest.mark.slow
def test_tiny_model_learns_the_synthetic_dynamics(tmp_path):
    data, heldout = str(tmp_path / "episodes"), str(tmp_path / "heldout")
    synthetic.generate(data, 200, image_size=(16, 16), seed=0, progress=False)
    synthetic.generate(heldout, 16, image_size=(16, 16), seed=10_000, progress=False)
    cfg = replace(load_config("tiny"), data=dict(path=data),
                  train=dict(workdir=str(tmp_path / "train"), steps=STEPS, progress=False, tensorboard=False,
                             ckpt_every=STEPS))
    m = train_and_evaluate(cfg, heldout)
    print(m)
    assert m["fd_psnr"] > m["copy_last_psnr"] + 0.5, "forward dynamics must beat repeating the last frame"
    assert m["fd_psnr"] > m["fd_shuffled_psnr"] + 0.5, "true actions must beat shuffled ones (actions are used)"
    assert m["id_mse"] < 0.7 * m["mean_action_mse"], "inverse dynamics must beat predicting the mean action"
    assert m["cvi_psnr"] > m["mean_frame_psnr"] + 1.0, "inpainting must beat the mean frame"
