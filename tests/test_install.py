"""A wheel (what ``pip install .`` installs, not the editable checkout) carries what the commands need: the named
configs list and `sc3 train --config tiny` trains from it, with the checkout nowhere on the path."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_a_wheel_lists_the_configs_and_trains_tiny(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", str(ROOT), "-w", str(tmp_path / "whl")],
                   check=True, cwd=tmp_path)
    wheel = next((tmp_path / "whl").glob("sc3_jax-*.whl"))
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
                   check=True)
    # the wheel's package first; its dependencies from this environment; run from elsewhere than the checkout
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("XLA_FLAGS", None)

    def sc3(*args, check=True):
        return subprocess.run([sys.executable, "-m", "sc3_jax.cli", *args], env=env, cwd=tmp_path,
                              capture_output=True, text=True, check=check)

    where = subprocess.run([sys.executable, "-c", "import sc3_jax; print(sc3_jax.__file__)"], env=env, cwd=tmp_path,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert where.startswith(str(site)), f"sc3_jax imported from {where}, not the wheel"
    names = [line.split()[0] for line in sc3("configs").stdout.splitlines()[1:]]
    assert {"tiny", "paper", "bussing_latent_gpu"} <= set(names), names
    data = tmp_path / "episodes"
    subprocess.run([sys.executable, "-c", "import sys; from sc3_jax.data import synthetic; "
                    "synthetic.generate(sys.argv[1], 4, length=24)", str(data)], env=env, cwd=tmp_path, check=True)
    run = sc3("train", "--config", "tiny", "--data.path", str(data), "--data.batch-size", "2", "--train.steps", "2",
              "--train.warmup-steps", "1", "--train.workdir", str(tmp_path / "w"), "--train.no-progress", check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = [json.loads(line) for line in (tmp_path / "w" / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 2
