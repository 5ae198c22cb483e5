"""Several results stores read as one: the shards of a sharded sweep (``sc3 sweep bench --shard I/N`` writes
``OUT/shard-I-of-N``), or stores given together to ``sc3 report A B ...``.

Stores merge only if they are shares of one sweep: the same config up to where and how the work ran (``out``,
``shard``, ``progress``, ``real_from``) and the modes each has added, and no rollout in two of them. Reading never
writes.
"""
from __future__ import annotations

import re
from pathlib import Path

from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import EVAL_MODES, ResultsStore

# fields that say where or how a share ran, not what it computed
_PLACEMENT = ("out", "shard", "progress", "real_from", "modes")


def shard_stores(root: Path) -> list[Path]:
    """The ``shard-I-of-N`` stores under ``root``, in shard order ([] if there are none)."""
    found = [(p, re.fullmatch(r"shard-(\d+)-of-(\d+)", p.name)) for p in root.glob("shard-*-of-*")]
    return [p for p, m in sorted(((p, m) for p, m in found if m), key=lambda x: int(x[1][1]))
            if (p / "sweep.json").exists()]


def open_store(results) -> ResultsStore | MergedStore:
    """A store from a path (a store, or a directory of shard stores) or several paths."""
    paths = [Path(results)] if isinstance(results, (str, Path)) else [Path(p) for p in results]
    expanded = []
    for p in paths:
        if (p / "sweep.json").exists():
            expanded.append(p)
        elif shard_stores(p):
            expanded += shard_stores(p)
        else:
            raise UserError(f"{p}: not a results store (no sweep.json, no shard-I-of-N stores): give a sweep's --out")
    if len(expanded) == 1:
        return ResultsStore(expanded[0])
    return MergedStore(expanded)


class MergedStore:
    """The read side of ``ResultsStore`` over several stores (records, config, arrays)."""

    def __init__(self, roots: list[Path]):
        self.stores = [ResultsStore(r) for r in roots]
        self.root = roots[0].parent if all(r.parent == roots[0].parent for r in roots) else roots[0]
        configs = [s.config() for s in self.stores]
        strip = lambda c: {k: v for k, v in c.items() if k not in _PLACEMENT}  # noqa: E731
        for s, c in zip(self.stores[1:], configs[1:]):
            # the benchmark's vocabulary (its splits' and criteria's order), recorded since a shard may have been
            # written: compared where both record it
            diff = sorted(k for k in strip(c).keys() | strip(configs[0]).keys()
                          if strip(c).get(k) != strip(configs[0]).get(k)
                          and not (k in ("splits", "criteria") and None in (c.get(k), configs[0].get(k))))
            if diff:
                raise UserError(f"{s.root} and {self.stores[0].root} are not shares of one sweep (they differ in "
                                 f"{', '.join(diff)}): report them separately")
        counts = {c.get("shard", "").partition("/")[2] for c in configs if c.get("shard")}
        if len(counts) > 1:
            raise UserError(f"{self.root}: shards of sweeps split {' and '.join(sorted(counts))} ways: keep one")
        modes = {m for c in configs for m in c["modes"]}
        self._config = dict(configs[0], out=str(self.root), shard=None,
                            modes=[m for m in EVAL_MODES if m in modes])
        self._where: dict[str, ResultsStore] = {}
        self._records = []
        for s in self.stores:
            for r in s.records():
                if r["id"] in self._where:
                    raise UserError(f"rollout {r['id']} is in both {self._where[r['id']].root} and {s.root}: "
                                     "the stores overlap, so they are not shares of one sweep")
                self._where[r["id"]] = s
                self._records.append(r)

    def config(self) -> dict:
        return dict(self._config)

    def records(self) -> list[dict]:
        return list(self._records)

    def done(self) -> set[str]:
        return set(self._where)

    def array_path(self, rid: str) -> Path:
        return (self._where.get(rid) or self.stores[0]).array_path(rid)

    def load_arrays(self, rid: str) -> dict:
        return (self._where.get(rid) or self.stores[0]).load_arrays(rid)
