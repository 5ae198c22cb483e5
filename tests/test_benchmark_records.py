"""The simulated benchmark's records do not move when the library generalises (issue 33: "README command 1 writes
records identical to today's"): a small `sc3 sweep` (real and online, evaluation, calibration and ceiling blocks,
the shipped world model and scorer) gives exactly the records and rollout arrays that the code before actions and
state became data (commit b64205e) wrote. tests/golden/benchmark_sweep.json was made by that commit:

    git archive b64205e | tar -x -C OLD && cd OLD && PYTHONPATH=OLD python -m sc3_jax.cli sweep --out G \\
        --world-model <this repo>/sc3_jax/evaluate/shipped/bussing_latent_gpu ARGS --degradations

(ARGS below; its boolean --degradations is today's "all"), then the records and a sha256 per array. A failure here
means the benchmark's numbers changed: a deliberate change regenerates the file and says why in the commit."""
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).parent / "golden" / "benchmark_sweep.json"
ARGS = ["--policies", "bus_bc_full", "bus_confused", "--episodes", "1", "--calibration-episodes", "1",
        "--ceiling-episodes", "1", "--episode-seconds", "1.6", "--workers", "1", "--no-progress", "--batch", "1"]


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16] + f" {a.dtype} {list(a.shape)}"


@pytest.mark.slow
def test_benchmark_sweep_records_and_arrays_are_todays(tmp_path):
    pytest.importorskip("mujoco")
    golden = json.loads(GOLDEN.read_text())
    out = tmp_path / "sweep"
    # as a user runs it: one device, XLA's default optimisation (the test processes' 8 devices and fast compile
    # move U in its 7th digit)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    subprocess.run([sys.executable, "-m", "sc3_jax.cli", "sweep", "--out", str(out), "--degradations", "all", *ARGS],
                   env=env, check=True, capture_output=True)
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    key = lambda r: (r["policy"], r["mode"], r["seed"])  # noqa: E731
    assert sorted(map(key, records)) == sorted(map(key, golden["records"]))
    want = {key(r): r for r in golden["records"]}
    for r in records:
        assert r == want[key(r)], f"record {key(r)} differs from commit {golden['commit']}'s"
    arrays = {str(p.relative_to(out)): {k: _digest(z[k]) for k in sorted(z.files)}
              for p in sorted((out / "rollouts").rglob("*.npz")) for z in [np.load(p)]}
    assert arrays == golden["arrays"]
