"""A sweep's results store and its vocabulary, shared by the sweep that writes it (``sweep.py``) and everything that
reads it (``report.py``, ``calibrate.py``, ``annotation.py``) without importing the sweep's machinery.

Store layout (``out/``): ``sweep.json`` (the sweep's config, checked on resume: records without it are never
resumed), ``results.jsonl`` (one JSON line per rollout, appended and flushed as each finishes; a line cut by a kill is
dropped on resume), ``rollouts/<policy>/<seed>_<mode>.npz`` (frames and arrays, written atomically before their
line). A damaged file is a ``UserError`` naming it (and the line), and changes nothing. An *archived* store keeps
``sweep.json`` and its records gzipped as ``results.jsonl.gz`` (a 20th of the size: how stores live in the
repository, ``docs/stores/``); it reads like any other and refuses to be written to (copy it and gunzip the copy).

*Evaluation modes* (``EVAL_MODES``, a record's ``"mode"``) say where a rollout ran: in the simulator ("real"), in the
world model replaying the real actions ("offline") or with the policy acting inside it ("online"). They are not the
*training modes* of ``training_modes.py`` (which tokens are noisy).
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from sc3_jax import atomic
from sc3_jax.errors import UserError
from sc3_jax.evaluate.metrics import OVERALL

EVAL_MODES = ("real", "offline", "online")
SPLITS = {"bussing": "in_distribution", "reverse": "out_of_distribution"}  # task -> split
# the order every report lists splits in, then the pooled one; derived so a new task's split cannot be missed
SPLIT_ORDER = (*dict.fromkeys(SPLITS.values()), OVERALL)


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
                raise UserError(f"{a} and {b} seeds overlap ({both[:3]}...): move calibration_seed0 / ceiling_seed0")
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
            if self.archived:
                raise UserError(f"{self.root} is an archived store (results.jsonl.gz, read-only): to add to it, copy "
                                "it and `gunzip` results.jsonl.gz in the copy; to reuse its real rollouts, give it "
                                "as --real-from")
            self._check_config(config)

    @property
    def archived(self) -> bool:
        """Its records are only in ``results.jsonl.gz`` (a store kept in the repository): read-only."""
        return not self.path.exists() and (self.root / "results.jsonl.gz").exists()

    def _check_config(self, config: dict):
        """Refuse (writing nothing) a store of another sweep, or one whose sweep is unknown or whose records do
        not read; then drop a line cut by a kill and write ``sweep.json``."""
        cfg_path = self.root / "sweep.json"
        # modes may be added to a store (records are per mode); anything else that changes results may not.
        # real_from only says where identical real rollouts were copied from (the source may move later)
        keep = lambda d: {k: v for k, v in d.items()  # noqa: E731
                          if k not in ("progress", "out", "modes", "perception_sha256", "real_from")}
        if cfg_path.exists():
            old = atomic.read_json(cfg_path, "restore it from a copy, or use another --out")
            # which perception weights scored the store (a store from before digests were kept: unknown, accepted)
            was, now = old.get("perception_sha256"), config.get("perception_sha256")
            if was and now and was != now:
                raise UserError(f"{self.root} was scored by other perception weights (sha256 {was}, these are "
                                f"{now}): re-score it first (`sc3 rescore {self.root}`, --perception WEIGHTS) or use "
                                "another --out")
            # a field added since the store was written is absent from it: it matches only at its neutral None
            diff = {k: (old.get(k), v) for k, v in keep(config).items() if old.get(k) != v}
            diff.update({k: (v, None) for k, v in keep(old).items() if k not in config})
            if diff:
                raise UserError(f"{self.root} holds results of a different sweep (changed: {diff}); use another "
                                "--out or delete it")
            config = dict(config, modes=[m for m in EVAL_MODES if m in set(old["modes"]) | set(config["modes"])])
        elif self.path.exists() and self.path.stat().st_size:
            # its records were run under a protocol nobody can check this one against: resuming could mix two
            raise UserError(f"{self.path} has no sweep.json beside it, so the sweep its records belong to is unknown: "
                            "restore sweep.json, or use another --out")
        self.records()  # a damaged record refuses the resume here, before anything is written
        self.root.mkdir(parents=True, exist_ok=True)
        self._repair()
        atomic.write_json(cfg_path, config)

    def config(self) -> dict:
        """The sweep's config as stored (``sweep.json``)."""
        return atomic.read_json(self.root / "sweep.json", "restore it from a copy of the store")

    def records(self) -> list[dict]:
        """Every complete line (a line cut by a kill, or still being written by a running sweep, is left out).
        Reading never writes: a report or another sweep may read a store while its sweep runs."""
        if self.archived:
            return atomic.read_jsonl(self.root / "results.jsonl.gz", "a rollout record", "restore the file")
        return atomic.read_jsonl(self.path, "a rollout record", "delete that line (resuming the sweep runs its "
                                 "rollout again) or restore the file")

    def _repair(self):
        """Before this store's own sweep appends to it: drop a line cut by a kill (atomic.drop_cut_line: nothing is
        lost if this is killed too) and the temporaries killed writers left in the store."""
        dropped = atomic.drop_cut_line(self.path)
        if dropped:
            print(f"{self.path}: dropped its last line, cut by a kill ({dropped} bytes); its rollout runs again",
                  file=sys.stderr)
        atomic.remove_stale(self.root, recursive=True)

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
        atomic.save_npz(self.array_path(rid), **arrays)

    def load_arrays(self, rid: str) -> dict:
        p = self.array_path(rid)
        with atomic.open_npz(p, f"restore it, or delete it and {rid}'s line in {self.path} and resume the sweep"
                                " to run it again") as z:
            return {k: z[k] for k in z.files}
