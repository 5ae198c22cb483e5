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

from sc3_jax.core import atomic, locks
from sc3_jax.core.errors import UserError
from sc3_jax.core.safe_names import ALLOWED, check_name, is_safe, join_inside
from sc3_jax.core.validate import is_finite_number, out_dir, regular_file
from sc3_jax.measures.metrics import OVERALL

EVAL_MODES = ("real", "offline", "online")


def criteria_order(config: Mapping, records=()) -> tuple[str, ...]:
    """A store's per-object criteria in their (cumulative) order: the benchmark's, as its sweep recorded them in
    sweep.json (``"criteria"``; a record's outcomes are written with sorted keys), else those of the first outcome of
    ``records`` (``metrics.criteria_of``) by name."""
    if config.get("criteria"):
        return tuple(config["criteria"])
    from sc3_jax.measures.metrics import criteria_of
    return tuple(sorted(next((criteria_of(o) for r in records for o in r.get("objects") or ()), ())))


def split_order(config: Mapping, records=()) -> list[str]:
    """The order a store's splits are reported in (the pooled one, ``metrics.OVERALL``, not among them): the
    benchmark's, as its sweep recorded it in sweep.json (``"splits"``, its in-distribution split first: tau is chosen
    there), then any other split of ``records`` by name (a store from before the record: every split by name)."""
    order = [s for s in config.get("splits") or () if s != OVERALL]
    return order + sorted({r["split"] for r in records if "split" in r} - set(order))


def rollout_id(policy: str, seed: int, mode: str) -> str:
    """A rollout's record id and the path of its arrays under ``rollouts/``: the policy's name is a directory
    (checked where a sweep starts and where a record is written: :func:`check_policy_names`)."""
    return f"{policy}/{int(seed)}_{mode}"


def check_policy_names(names) -> None:
    """Each policy's name becomes a directory of the store: a one-line error, before any rollout, for one that
    cannot (``ws://HOST:PORT`` unnamed, say)."""
    for n in names:
        check_name(n, "policy name (give the policy a name: --policies NAME=SPEC)")


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


def _cut(path: Path) -> int:
    """The bytes after the last newline of ``path`` (0: none, or no such file); reads only the file's end."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 65536))
            tail = fh.read()
    except (FileNotFoundError, IsADirectoryError):
        return 0
    return 0 if not tail or tail.endswith(b"\n") else len(tail) - tail.rfind(b"\n") - 1


class ResultsStore:
    """Append-only JSONL of rollout records + one npz of arrays per rollout."""

    def __init__(self, root: str | Path, config: dict | None = None, lock: bool = False):
        """``config``: open to write (checked against ``sweep.json``). ``lock``: hold the store's lock until
        :meth:`close`, so that a second sweep on it stops with one line (what the sweeps do); taken after the
        checks, before anything is written."""
        self.root = Path(root)
        self.path = self.root / "results.jsonl"
        self._lock: locks.Lock | None = None
        self._locking = lock
        self._reader = config is None  # a writer's resume drops a cut last line (``_repair``); a reader refuses it
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
        out_dir(self.root, "--out")  # a file there (or above): one line before the first rollout, not after it
        cfg_path = self.root / "sweep.json"
        # modes may be added to a store (records are per mode); anything else that changes results may not.
        # real_from only says where identical real rollouts were copied from (the source may move later)
        keep = lambda d: {k: v for k, v in d.items()  # noqa: E731
                          if k not in ("progress", "out", "modes", "perception_sha256", "real_from", "splits",
                                        "criteria")}
        if cfg_path.exists() and self._holds_results():
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
        if self._locking:  # before the repair: a running sweep's line being written is not a cut line
            self._lock = locks.Lock(self.root, "sweep")
        self._repair()
        atomic.write_json(cfg_path, config)

    def _holds_results(self) -> bool:
        """Whether any rollout of this store was kept (a record or its arrays): a store holding only the
        ``sweep.json`` of a sweep that failed before its first rollout (a scorer that raised) is taken by the
        corrected command, not refused as "a different sweep"."""
        rollouts = self.root / "rollouts"
        return (self.path.exists() and self.path.stat().st_size > 0) or (
            rollouts.is_dir() and any(p.is_file() for p in rollouts.rglob("*")))

    def close(self) -> None:
        """Give the store's lock back (a store opened without ``lock`` holds none)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def config(self) -> dict:
        """The sweep's config as stored (``sweep.json``)."""
        from sc3_jax.core.validate import json_object

        fix = "restore it from a copy of the store"
        path = self.root / "sweep.json"
        if path.exists() or path.is_symlink():  # the store's own: not another store's protocol through a link
            regular_file(path, fix, inside=self.root)
        return json_object(atomic.read_json(path, fix), str(path), fix)

    def records(self) -> list[dict]:
        """Every complete line (a line cut by a kill, or still being written by a running sweep, is left out).
        Reading never writes: a report or another sweep may read a store while its sweep runs. A store opened to
        read (no ``config``) refuses a cut last line that no running sweep is writing."""
        return self._read(strict=self._reader)

    def _read(self, strict: bool) -> list[dict]:
        if self.archived:
            path, fix = self.root / "results.jsonl.gz", "restore the file"
        else:
            path, fix = self.path, "delete that line (resuming the sweep runs its rollout again) or restore the file"
        if path.exists() or path.is_symlink():  # the store's own file: no link to another store's records, no FIFO
            regular_file(path, "restore the file from a copy of the store", inside=self.root)
        cut = strict and not self.archived and _cut(path)
        if cut and not locks.held(self.root):
            # a last line cut while no sweep writes it: a sweep killed mid-line, or a file cut short (half a store
            # reads as a complete one); a report of it would silently leave rollouts out
            raise UserError(f"{path}: its last line is cut ({cut} bytes without a newline) and no sweep is "
                            "writing it: resume the sweep (it drops that line and runs its rollout again) or restore "
                            "the file")
        records = atomic.read_jsonl(path, "a rollout record", fix)
        check_records(records, path, fix)
        return records

    def _repair(self):
        """Before this store's own sweep appends to it: drop a line cut by a kill (atomic.drop_cut_line: nothing is
        lost if this is killed too) and the temporaries killed writers left in the store."""
        dropped = atomic.drop_cut_line(self.path)
        if dropped:
            print(f"{self.path}: dropped its last line, cut by a kill ({dropped} bytes); its rollout runs again",
                  file=sys.stderr)
        atomic.remove_stale(self.root, recursive=True)

    def done(self) -> set[str]:
        """The ids of the rollouts kept (a cut last line is not one: the sweep that resumes runs it again)."""
        return {r["id"] for r in self._read(strict=False)}

    def append(self, records: list[dict]):
        lines = []
        check_policy_names({r["policy"] for r in records if "policy" in r})
        for r in records:
            try:  # a NaN or inf in a record would read back as a silent rate: refused, nothing written
                lines.append(json.dumps(r, sort_keys=True, allow_nan=False) + "\n")
            except ValueError:
                raise UserError(f"rollout {r.get('id')}: its record holds a non-finite number "
                                f"({_non_finite_fields(r)}); nothing of it was written") from None
        with open(self.path, "a") as fh:
            fh.write("".join(lines))
            fh.flush()
            os.fsync(fh.fileno())

    def array_path(self, rid: str) -> Path:
        return join_inside(self.root / "rollouts", f"{rid}.npz")  # ids are read from a store someone handed over

    def save_arrays(self, rid: str, **arrays):
        check_actions(rid, arrays.get("actions"), arrays.get("u_raw"))
        atomic.save_npz(self.array_path(rid), **arrays)

    def load_arrays(self, rid: str) -> dict:
        p = self.array_path(rid)
        fix = f"restore it, or delete it and {rid}'s line in {self.path} and resume the sweep to run it again"
        regular_file(p, fix, inside=self.root)  # a store's arrays are its own: no link into another store, no FIFO
        with atomic.open_npz(p, fix) as z:
            return {k: z[k] for k in z.files}


def paired_frames(store, policy: str, seed: int, stride: int | None = None):
    """(real frames [V, T, ...], online frames [V, n, ...] at the model's rate, the real frame index of each online
    one, offline frames or None) of one condition of ``store``; None if its real or online arrays are not kept.
    ``stride``: the online record's (None: read from the store's records)."""
    ids = {m: rollout_id(policy, seed, m) for m in EVAL_MODES}
    if not all(store.array_path(ids[m]).exists() for m in ("real", "online")):
        return None
    real, online = (store.load_arrays(ids[m])["frames"] for m in ("real", "online"))
    if stride is None:
        stride = next(r for r in store.records() if r["id"] == ids["online"])["stride"]
    at = np.minimum(np.arange(online.shape[1]) * stride, real.shape[1] - 1)
    offline = store.load_arrays(ids["offline"])["frames"] if store.array_path(ids["offline"]).exists() else None
    return real, online, at, offline


def check_actions(rid: str, actions, u_raw=None) -> None:
    """A policy's actions must be finite, and so must the uncertainty they give (1e30 overflows U_chunk to inf, which
    a tau reads as "terminate": a silent success). One line naming the rollout (its id starts with the policy)."""
    for what, x in (("actions", actions), ("U_chunk of its actions", u_raw)):
        if x is not None and not np.all(np.isfinite(x)):
            a = np.abs(np.asarray(actions if actions is not None else 0.0, np.float64))
            raise UserError(f"rollout {rid}: the policy's {what} are not finite (largest finite |action| "
                            f"{a[np.isfinite(a)].max(initial=0):.3g}): fix the policy; nothing of this rollout was "
                            "written")


# what a record's outcome fields hold; a record of one mode carries the same of them as every other of its mode
OUTCOME_FIELDS = ("outcomes", "outcomes_by_cut", "objects", "perception", "u", "u_raw")


def check_records(records: list[dict], path: Path, fix: str) -> None:
    """Every record of a store as the report reads it: an outcome that is not ``true`` / ``false`` (``2``,
    ``"yes"``, a list), a U that is not a finite number, a missing outcome, is one line naming the record, never a
    silent rate (``success: 2`` read as 1.00 [0.00, 2.00]) or a traceback in the report."""
    first: dict[str, dict] = {}
    seen: dict[str, int] = {}
    for i, r in enumerate(records, 1):
        def bad(problem: str):
            raise UserError(f"{path}: record {i} ({r.get('id')!r}): {problem}; {fix}")
        if not isinstance(r.get("id"), str) or r.get("mode") not in EVAL_MODES:
            bad(f"needs a text id and a mode of {list(EVAL_MODES)}")
        if r["id"] in seen:  # a sweep writes each rollout once: a second line would silently replace the first
            bad(f"the same rollout as record {seen[r['id']]}")
        seen[r["id"]] = i
        if "policy" in r and not is_safe(r["policy"]):  # a directory of the store, a name every report prints
            bad(f"policy name {r['policy']!r} is not one a sweep writes ({ALLOWED})")
        for k in ("seed", "num_chunks", "stride", "length", "score_stride"):
            if k in r and not (isinstance(r[k], int) and not isinstance(r[k], bool) and r[k] >= 0):
                bad(f"{k} is {r[k]!r}, expected a whole number")
        if "success" in r and not isinstance(r["success"], bool):
            bad(f"success is {r['success']!r}, expected true or false")
        if "outcomes" in r:
            _check_outcomes(r["outcomes"], "outcomes", bad)
        if "outcomes_by_cut" in r:
            cuts = r["outcomes_by_cut"]
            if not isinstance(cuts, dict):
                bad(f"outcomes_by_cut is {cuts!r}, expected {{chunks kept: outcomes}}")
            for cut, o in cuts.items():
                _check_outcomes(o, f"outcomes_by_cut[{cut!r}]", bad)
        for k in ("objects", "perception"):
            # an object is names (strings) and criteria (true / false), whichever the benchmark's criteria are
            if k in r and not (isinstance(r[k], list) and all(isinstance(o, dict) and all(
                    isinstance(v, (bool, str)) for v in o.values()) for o in r[k])):
                bad(f"{k} must be a list of objects whose criteria are true or false")
        for k in ("u", "u_raw"):
            # U_chunk is a distance between action chunks: a negative one is no U a sweep measured
            if k in r and not (isinstance(r[k], list) and all(is_finite_number(x) and x >= 0 for x in r[k])):
                bad(f"{k} must be a list of finite numbers >= 0 (U_chunk, a distance)")
        # one mode, one layout: a record missing an outcome (or with other criteria) would drop out of a rate
        have = {k: sorted(r["outcomes"]) if k == "outcomes" else True for k in OUTCOME_FIELDS if k in r}
        ref = first.setdefault(r["mode"], have)
        if have != ref:
            bad(f"carries {have} where the store's other {r['mode']} records carry {ref}")


def _check_outcomes(o, what: str, bad) -> None:
    if not (isinstance(o, dict) and o and all(isinstance(v, bool) for v in o.values())):
        bad(f"{what} is {o!r}, expected {{criterion: true | false}}")


def _non_finite_fields(record: dict) -> str:
    """Which fields of a record hold NaN or inf (for the message)."""
    def bad(v) -> bool:
        if isinstance(v, float):
            return not np.isfinite(v)
        if isinstance(v, Mapping):
            return any(bad(x) for x in v.values())
        if isinstance(v, (list, tuple)):
            return any(bad(x) for x in v)
        return False
    return ", ".join(k for k, v in record.items() if bad(v)) or "?"
