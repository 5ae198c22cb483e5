"""Human annotation: a blinded export of every rollout of a sweep and a validating import of the filled CSV.

Blinding: every rollout (real, offline, online) becomes one mp4 with the three views side by side, at the world
model's frame rate and one length (real rollouts are subsampled to that rate; a real episode that ended early is
held on its last frame, as the scene was then at rest), named by a random id, in shuffled order. Nothing in the
export names the source: the key (clip id -> rollout id) is written to a *separate* file that the annotators do not
get. The CSV template has one row per clip x object with the instruction and empty ``language, lifting, placing``
cells to fill with 0/1 (criteria as in docs/sim.md).

    export_blinded("runs/sweep", "runs/annotate", key_path="runs/annotate_key.json")
    labels = import_annotations("runs/annotate/annotations.csv", "runs/annotate_key.json")
    HumanScorer(labels)   # a scorer like the others (scorers.py)
"""
from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.evaluation.results import ResultsStore

from .tasks import CRITERIA

COLUMNS = ("clip_id", "instruction", "object") + CRITERIA


class AnnotationError(ValueError):
    """A filled CSV that cannot be imported; the message lists every offending row/id."""


def _clip(store: ResultsStore, rec: dict, stride: int, length: int) -> np.ndarray:
    frames = store.load_arrays(rec["id"])["frames"]  # [V, T, H, W, 3]
    if rec["mode"] == "real":
        frames = frames[:, ::stride]
    if frames.shape[1] < length:
        frames = np.concatenate([frames, np.repeat(frames[:, -1:], length - frames.shape[1], 1)], 1)
    return np.concatenate(list(frames[:, :length]), axis=2)  # views side by side: [T, H, V*W, 3]


def export_blinded(results: str | Path, out: str | Path, key_path: str | Path | None = None, seed: int = 0,
                   fps: int = 10) -> tuple[Path, Path]:
    """Write ``out/clips/<id>.mp4``, ``out/annotations.csv`` (template) and the key (default ``<out>_key.json``,
    outside ``out``). Returns (csv path, key path)."""
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition
    from sc3_jax.core.video import write_mp4
    store = ResultsStore(results)
    recs = store.records()
    if not recs:
        raise ValueError(f"{results}: no rollouts to export")
    imagined = [r for r in recs if r["mode"] != "real"]
    stride = imagined[0]["stride"] if imagined else 1
    length = max(r["num_chunks"] * r["frames_per_chunk"] + 1 for r in imagined) if imagined else \
        max(r["length"] for r in recs)
    out = Path(out)
    key_path = Path(key_path) if key_path else out.parent / f"{out.name}_key.json"
    (out / "clips").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(recs))
    ids = [f"{x:08x}" for x in rng.choice(16 ** 8, size=len(recs), replace=False)]
    key, rows = {}, []
    for cid, i in zip(ids, order):
        rec = recs[i]
        write_mp4(out / "clips" / f"{cid}.mp4", _clip(store, rec, stride, length), fps)
        ic = make_initial_condition(rec["seed"], rec["task"])
        key[cid] = {"rollout": rec["id"], "objects": list(ic.objects)}
        rows += [{"clip_id": cid, "instruction": ic.prompt, "object": o} for o in ic.objects]
    text = io.StringIO(newline="")  # the csv module's own line ends (\r\n), as a file opened with newline=""
    w = csv.DictWriter(text, COLUMNS)
    w.writeheader()
    w.writerows(rows)
    atomic.write_text(out / "annotations.csv", text.getvalue())
    atomic.write_json(key_path, key)
    return out / "annotations.csv", key_path


def import_annotations(csv_path: str | Path, key_path: str | Path) -> dict[tuple[str, str], dict[str, bool]]:
    """The filled CSV -> ``{(rollout id, object): {criterion: bool}}``. Raises :class:`AnnotationError` for missing
    columns, unknown clip ids, unknown objects, duplicate or missing rows, and values other than 0/1."""
    key = atomic.read_json(key_path, "restore it from a copy, or export the same sweep again with the same "
                          "seed (the same clip ids)")
    with open(csv_path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing_cols = [c for c in ("clip_id", "object") + CRITERIA if c not in (reader.fieldnames or [])]
        if missing_cols:
            raise AnnotationError(f"{csv_path}: missing columns {missing_cols} (expected {list(COLUMNS)})")
        rows = list(reader)
    problems, labels = [], {}
    for n, row in enumerate(rows, start=2):  # line numbers as a spreadsheet shows them (header = 1)
        cid, obj = (row["clip_id"] or "").strip(), (row["object"] or "").strip()
        if cid not in key:
            problems.append(f"line {n}: unknown clip id {cid!r}")
            continue
        if obj not in key[cid]["objects"]:
            problems.append(f"line {n}: clip {cid} has no object {obj!r} (it shows {key[cid]['objects']})")
            continue
        values = {}
        for c in CRITERIA:
            v = (row[c] or "").strip()
            if v not in ("0", "1"):
                problems.append(f"line {n}: {c}={v!r} (expected 0 or 1)")
            values[c] = v == "1"
        k = (key[cid]["rollout"], obj)
        if k in labels:
            problems.append(f"line {n}: duplicate row for clip {cid}, object {obj}")
        labels[k] = values
    expected = {(v["rollout"], o): cid for cid, v in key.items() for o in v["objects"]}
    missing = [f"{cid}/{o}" for (r, o), cid in expected.items() if (r, o) not in labels]
    if missing:
        problems.append(f"missing rows (clip/object): {missing[:20]}{' ...' if len(missing) > 20 else ''}")
    if problems:
        raise AnnotationError(f"{csv_path}: {len(problems)} problem(s):\n  " + "\n  ".join(problems))
    return labels
