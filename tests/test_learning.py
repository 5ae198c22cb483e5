"""Learning is real: `sc3 demo` (the tiny config trained for a few CPU-minutes on the synthetic environment) beats
the baseline each capability must beat, on held-out episodes (sc3_jax/evaluate/world_model.py). Runs the CLI in a
subprocess with XLA's full optimisations (the other tests compile without them; this one is bound by run time)."""
import json
import subprocess
import sys

import pytest

from conftest import optimised_env

STEPS = 1200


@pytest.mark.slow
@pytest.mark.timeout(1800)  # ~10 min alone on 2 cores
def test_tiny_model_learns_the_synthetic_dynamics(tmp_path):
    subprocess.run([sys.executable, "-m", "sc3_jax.cli", "demo", "--out", str(tmp_path), "--steps", str(STEPS)],
                   env=optimised_env(), check=True, timeout=1800)
    m = json.loads((tmp_path / "demo_metrics.json").read_text())
    print(m)
    assert m["fd_psnr"] > m["copy_last_psnr"] + 0.5, "forward dynamics must beat repeating the last frame"
    assert m["fd_psnr"] > m["fd_shuffled_psnr"] + 0.5, "true actions must beat shuffled ones (actions are used)"
    assert m["id_mse"] < 0.7 * m["mean_action_mse"], "inverse dynamics must beat predicting the mean action"
    assert m["cvi_psnr"] > m["mean_frame_psnr"] + 1.0, "inpainting must beat the mean frame"
