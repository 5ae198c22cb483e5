"""A sweep's results store and its vocabulary, shared by the sweep that writes it (``sweep.py``) and everything that
reads it (``report.py``, ``calibrate.py``, ``annotation.py``) without importing the sweep's machinery.

Store layout (``out/``): ``sweep.json`` (the sweep's config, checked on resume), ``results.jsonl`` (one JSON line
per rollout, appended and flushed as each finishes), ``rollouts/<policy>/<seed>_<mode>.npz`` (frames and arrays,
written before their line).

*Evaluation modes* (``EVAL_MODES``, a record's ``"mode"``) say where a rollout ran: in the simulator ("real"), in the
world model replaying the real actions ("offline") or with the policy acting inside it ("online"). They are not the
*training modes* of ``training_modes.py`` (which tokens are noisy).
"""
from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

EVAL_MODES = ("real", "offline", "online")
SPLITS = {"bussing": "in_distribution", "reverse": "out_of_distribution"}  # task -> split


def rollout_id(policy: str, seed: int, mode: str) -> str:
    return f"{policy}/{seed}_{mode}"


def seed_blocks(cfg) -> dict[str, list[int]]:
    """Disjoint simulator-seed blocks: evaluation, calibration (tau), ceiling (second real set), from a
    ``SweepConfig`` or its ``sweep.json`` (a block whose keys are missing is empty). Raises if they overlap: a
    calibration or ceiling rollout on an evaluation seed would leak the evaluation into its baseline."""
    d = cfg if isinstance(cfg, Mapping) else dataclasses.asdict(cfg)
    block = lambda k0, kn: [d[k0] + i for i in range(d.get(kn) or 0)] if k0 in d else []  # noqa: E731
    blocks = {"evaluation": block("seed0", "episodes"),
              "calibration": block("calibration_seed0", "calibration_episodes"),
              "ceiling": block("ceiling_seed0", "ceiling_episodes")}
    names = list(blocks)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            both = sorted(set(blocks[a]) & set(blocks[b]))
            if both:
                raise ValueError(f"{a} and {b} seeds overlap ({both[:3]}...): move calibration_seed0 / ceiling_seed0")
    return blocks


REAL_ONLY_STRIDE = 2  # a sweep without a world model scores real frames at 10 Hz, the rollouts' rate


def score_strides(records: list[dict]) -> dict[str, int]:
    """The frame stride each real record of a store was scored at: its ``score_stride``, or for a record from
    before that field the store's world-model stride (``REAL_ONLY_STRIDE`` where it has no world-model rollouts)."""
    wm_stride = next((r["stride"] for r in records if "stride" in r), REAL_ONLY_STRIDE)
    return {r["id"]: r.get("score_stride", wm_stride) for r in records if r["mode"] == "real"}


def terminated_at(u: np.ndarray, tau: float) -> np.ndarray:
    """First chunk with U > tau per episode (-1: never). ``u`` [B, N]. Cutting a ``tau=inf`` rollout with this gives
    exactly the termination a rollout run with ``tau`` reports (``rollout.Rollout``)."""
    above = np.asarray(u) > tau
    return np.where(above.any(-1), above.argmax(-1), -1).astype(np.int32)


class ResultsStore:
    """Append-only JSONL of rollout records + one npz of arrays per rollout."""

    def __init__(self, root: str | Path, config: dict | None = None):
        self.root = Path(root)
        self.path = self.root / "results.jsonl"
        if config is not None:
            self._check_config(config)

    def _check_config(self, config: dict):
        self.root.mkdir(parents=True, exist_ok=True)
        cfg_path = self.root / "sweep.json"
        # modes may be added to a store (records are per mode); anything else that changes results may not.
        # real_from only says where identical real rollouts were copied from (the source may move later)
        keep = lambda d: {k: v for k, v in d.items()  # noqa: E731
                          if k not in ("progress", "out", "modes", "perception_sha256", "real_from")}
        if cfg_path.exists():
            old = json.loads(cfg_path.read_text())
            # which perception weights scored the store (a store from before digests were kept: unknown, accepted)
            was, now = old.get("perception_sha256"), config.get("perception_sha256")
            if was and now and was != now:
                raise ValueError(f"{self.root} was scored by other perception weights (sha256 {was}, these are "
                                 f"{now}): re-score it first (`sc3 rescore {self.root}`, --perception WEIGHTS) or use "
                                 "another --out")
            # a field added since the store was written is absent from it: it matches only at its neutral None
            diff = {k: (old.get(k), v) for k, v in keep(config).items() if old.get(k) != v}
            diff.update({k: (v, None) for k, v in keep(old).items() if k not in config})
            if diff:
                raise ValueError(f"{self.root} holds results of a different sweep (changed: {diff}); use another "
                                 "--out or delete it")
            config = dict(config, modes=[m for m in EVAL_MODES if m in set(old["modes"]) | set(config["modes"])])
        cfg_path.write_text(json.dumps(config, indent=1))
        self._repair()

    def config(self) -> dict:
        """The sweep's config as stored (``sweep.json``)."""
        return json.loads((self.root / "sweep.json").read_text())

    def records(self) -> list[dict]:
        """Every complete line (a line cut by a kill, or still being written by a running sweep, is left out).
        Reading never writes: a report or another sweep may read a store while its sweep runs."""
        if not self.path.exists():
            return []
        raw = self.path.read_bytes()
        raw = raw[:raw.rfind(b"\n") + 1]
        return [json.loads(line) for line in raw.decode().splitlines() if line.strip()]

    def _repair(self):
        """Truncate a line cut by a kill, before this store's own sweep appends to it."""
        if self.path.exists():
            raw = self.path.read_bytes()
            if raw and not raw.endswith(b"\n"):
                self.path.write_bytes(raw[:raw.rfind(b"\n") + 1])

    def done(self) -> set[str]:
        return {r["id"] for r in self.records()}

    def append(self, records: list[dict]):
        with open(self.path, "a") as fh:
            fh.write("".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
            fh.flush()
            os.fsync(fh.fileno())

    def array_path(self, rid: str) -> Path:
        return self.root / "rollouts" / f"{rid}.npz"

    def save_arrays(self, rid: str, **arrays):
        p = self.array_path(rid)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, p)

    def load_arrays(self, rid: str) -> dict:
        with np.load(self.array_path(rid)) as z:
            return {k: z[k] for k in z.files}
