"""Re-score a sweep's results store with other perception weights, without re-running a single rollout.

A store keeps every rollout's frames (``rollouts/ID.npz``), so when the scorer improves the hours of rollouts behind
a store need not be redone: ``sc3 rescore RESULTS [--perception WEIGHTS]`` reads each rollout's frames again exactly
as the sweep read them (real: every ``score_stride``-th frame and the last, clean and degraded; imagined: every frame,
cut after each chunk) and rewrites the perception-scored fields (real: ``perception``, ``perception_degraded``;
offline / online: ``objects``, online also ``objects_by_cut``). Physics outcomes, U_chunk and PSNR are left as they
are. The new results.jsonl replaces the old one atomically, and sweep.json records the weights
(``perception``, ``perception_sha256``), so a resumed sweep refuses to mix scorers (``ResultsStore``).

The rollouts themselves do not change: inside an imagined rollout the policy's gripper state was read from the
frames by the weights of that time (``SweepConfig.state_reader``, None = the scorer's). Re-scoring such a store with
other weights therefore asks for those (``--state-reader OLD_WEIGHTS``, checked against the recorded digest), writes
them into sweep.json, and the sweep is resumed with the same ``--state-reader``: its remaining rollouts are made the
way the first ones were.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import ResultsStore, score_strides


def weights_digest(path: str | Path) -> str:
    """The first 16 hex digits of the weights file's SHA-256: which scorer read a store."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def rescore(results: str | Path, weights: str | Path | None = None, state_reader: str | Path | None = None,
            progress: bool = True) -> dict[str, int]:
    """Re-score every rollout of the store ``results`` with ``weights`` (None: the shipped ones); returns the number
    of rollouts per mode whose perception-scored outcomes changed. ``state_reader``: see the module docstring."""
    from tqdm import tqdm

    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.evaluation.scorers import RolloutView
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition
    store = ResultsStore(results)
    if store.archived:
        raise UserError(f"{results}: an archived store (results.jsonl.gz) is read-only: re-score a copy with "
                        "results.jsonl.gz gunzipped")
    recs = store.records()
    if not recs:
        raise UserError(f"{results}: no rollouts to re-score")
    path = Path(weights) if weights is not None else perception.DEFAULT_WEIGHTS
    cfg, digest = store.config(), weights_digest(path)
    was = cfg.get("perception_sha256")
    if any(r["mode"] != "real" for r in recs) and not cfg.get("state_reader") and was != digest:
        # the imagined rollouts read the gripper state with the scorer of their time: the store must remember it
        if state_reader is None:
            raise UserError(f"{results}: its imagined rollouts read the gripper state with the perception weights "
                            f"that scored them (sha256 {was or 'not recorded'}); pass those as --state-reader, "
                            "and resume the sweep with the same --state-reader")
        if was and weights_digest(state_reader) != was:
            raise UserError(f"--state-reader {state_reader} (sha256 {weights_digest(state_reader)}) is not the "
                            f"weights the store was scored with (sha256 {was})")
        cfg["state_reader"] = str(state_reader)
    scorer = PerceptionScorer(perception.load(path))
    strides = score_strides(recs)
    changed: dict[str, int] = {}
    out = []
    for r in tqdm(recs, desc="rescore", unit="rollout", disable=not progress):
        frames = store.load_arrays(r["id"])["frames"]
        ic = make_initial_condition(r["seed"], r["task"])
        new = dict(r)
        if r["mode"] == "real":
            view = RolloutView(r["id"], frames, ic.objects, ic.destinations())
            new["perception"], degraded = scorer.score_real(view, r["seed"], strides[r["id"]],
                                                            "perception_degraded" in r)
            if degraded:
                new["perception_degraded"] = degraded
        else:
            cuts = scorer.score_cuts(frames, ic.objects, ic.destinations(), r["frames_per_chunk"], r["num_chunks"],
                                     prefix=1)
            new["objects"] = cuts[-1]
            if "objects_by_cut" in r:
                new["objects_by_cut"] = cuts
        new = json.loads(json.dumps(new, sort_keys=True))  # as the store writes and reads it back
        changed[r["mode"]] = changed.get(r["mode"], 0) + (new != r)
        out.append(new)
    atomic.write_text(store.path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in out))
    cfg.update(perception=None if weights is None else str(weights), perception_sha256=digest)
    atomic.write_json(store.root / "sweep.json", cfg)
    return changed
