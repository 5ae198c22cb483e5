"""The simulated benchmark's records do not move when the library generalises ("README command 1 writes
records identical to today's"): a small `sc3 sweep bench` (real and online, evaluation, calibration and ceiling blocks,
the shipped world model and scorer) gives exactly the records and rollout arrays that the code before actions and
state became data (commit b64205e) wrote. tests/golden/benchmark_sweep.json was made by that commit:

    git archive b64205e | tar -x -C OLD && cd OLD && PYTHONPATH=OLD python -m sc3_jax.cli sweep --out G \\
        --world-model <this repo>/sc3_jax/benchmarks/bussing/shipped/bussing_latent_gpu ARGS --degradations

(ARGS below; its boolean --degradations is today's "all"), then the records and each array's dtype, shape, mean and
mean absolute value. Floats are compared to a relative 1e-4 (records) and 1e-3 (array means): XLA's CPU numerics move
with the machine and the jax build (U in its 7th digit, a few rendered pixels: the file was regenerated from b64205e on
2026-11-28 when CI's machine moved, with today's code bit-identical to it there), while a change to the benchmark
moves outcomes, shapes or means far more. A failure here means the benchmark's numbers changed: a deliberate change
regenerates the file and says why in the commit."""
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


def _close(got, want, path: str = "") -> list[str]:
    """Where ``got`` differs from ``want``: floats beyond a relative 1e-4, anything else at all."""
    if isinstance(want, dict) and isinstance(got, dict):
        return [d for k in sorted(set(got) | set(want)) for d in _close(got.get(k), want.get(k), f"{path}.{k}")]
    if isinstance(want, list) and isinstance(got, list) and len(got) == len(want):
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in _close(g, w, f"{path}[{i}]")]
    if isinstance(want, float) and isinstance(got, float):
        return [] if abs(got - want) <= 1e-4 * abs(want) + 1e-7 else [f"{path}: {got} != {want}"]
    return [] if got == want else [f"{path}: {got!r} != {want!r}"]


def _summary(a: np.ndarray) -> dict:
    return {"dtype": str(a.dtype), "shape": list(a.shape), "mean": float(np.mean(a, dtype=np.float64)),
            "mean_abs": float(np.mean(np.abs(a.astype(np.float64))))}


@pytest.mark.slow
def test_benchmark_sweep_records_and_arrays_are_todays(tmp_path):
    pytest.importorskip("mujoco")
    golden = json.loads(GOLDEN.read_text())
    out = tmp_path / "sweep"
    # as a user runs it: one device, XLA's default optimisation (the test processes' 8 devices and fast compile
    # move U in its 7th digit)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    subprocess.run([sys.executable, "-m", "sc3_jax.cli", "sweep", "bench", "--out", str(out), "--degradations", "all",
                    *ARGS],
                   env=env, check=True, capture_output=True)
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    key = lambda r: (r["policy"], r["mode"], r["seed"])  # noqa: E731
    assert sorted(map(key, records)) == sorted(map(key, golden["records"]))
    want = {key(r): r for r in golden["records"]}
    for r in records:
        assert not _close(r, want[key(r)]), f"record {key(r)} differs from commit {golden['commit']}'s: " \
            + "; ".join(_close(r, want[key(r)])[:5])
    arrays = {str(p.relative_to(out)): {k: _summary(z[k]) for k in sorted(z.files)}
              for p in sorted((out / "rollouts").rglob("*.npz")) for z in [np.load(p)]}
    assert arrays.keys() == golden["arrays"].keys()
    for name, fields in golden["arrays"].items():
        assert arrays[name].keys() == fields.keys(), name
        for k, w in fields.items():
            g = arrays[name][k]
            assert (g["dtype"], g["shape"]) == (w["dtype"], w["shape"]), f"{name} {k}"
            scale = 1e-3 * w["mean_abs"] + 1e-6
            assert abs(g["mean"] - w["mean"]) <= scale and abs(g["mean_abs"] - w["mean_abs"]) <= scale, \
                f"{name} {k}: mean {g['mean']:.6g} / |{g['mean_abs']:.6g}| against {w['mean']:.6g} / |{w['mean_abs']:.6g}|"


def test_the_golden_comparison_tolerates_float_noise_and_not_changes():
    rec = {"u": [0.5783365964889526], "outcome": "lifting", "seed": 1}
    assert not _close({**rec, "u": [0.5783365368843079]}, rec)  # the 7th digit (CI's machine, 2026-11-28)
    assert _close({**rec, "u": [0.579]}, rec)
    assert _close({**rec, "outcome": "placing"}, rec)
    assert _close({**rec, "u": []}, rec)
