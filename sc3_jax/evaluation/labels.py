"""Real outcomes of the evaluated policies, for ``sc3 sweep episodes --data ... --real SOURCE``: per real episode,
the policy that ran it and ``{criterion: bool}``. They are the reference the imagined ranking is compared with
(``report_episodes.py``); nothing here is rolled out.

A SOURCE is ``PATH`` or ``NAME=PATH`` (then every episode of PATH is policy NAME's, whatever it says):

* an episode store (``dataset.json``; ``data/episodes.py``): each episode's ``meta.json`` holds
  ``"policy": NAME`` (``POLICY_FIELD``) and ``"labels": {criterion: bool, ...}`` (``LABELS_FIELD``; entries that
  are not booleans, such as ``sc3 sim demos``' per-object lists, are not criteria). ``sc3 data import-lerobot``
  keeps a dataset's ``next.success`` as ``"labels": {"success": ...}``; a store imported before it did (its meta
  keeps ``lerobot_root`` and ``episode_index``) whose episodes carry no boolean labels reads ``next.success`` from
  that LeRobot dataset instead;
* a LeRobot dataset (``meta/info.json``), given as ``NAME=PATH``: an episode succeeded when any of its frames has
  ``next.success`` true (LeRobot's own evaluation reduces it with ``any``), the criterion ``success``;
* a CSV file (``.csv``): a header row with a ``policy`` column (optional with ``NAME=``), an optional ``episode``
  column, and one column per criterion holding true/false, 1/0 or yes/no; one row per real episode.

Policies are matched to the sweep's by name: the NAME of ``--policies NAME=SPEC`` (a bare spec's name is the spec).
Every problem is a one-line UserError naming the file and the field.

A sweep keeps the outcomes it was given in its store (``keep``: the episodes as read, in ``real.json``), and its
report reads them from there (``kept``), never from a path: a path names a file on the machine that ran the sweep,
and resolved here it reads whatever the current directory holds under that name.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.core.validate import json_object, regular_file, same_files

POLICY_FIELD = "policy"  # meta.json: the name of the policy that ran the episode
LABELS_FIELD = "labels"  # meta.json: {criterion: bool}
LEROBOT_SUCCESS = "next.success"  # LeRobot's per-frame success column
TRUE, FALSE = ("true", "1", "yes", "y", "t"), ("false", "0", "no", "n", "f")
KEPT_FORMAT = 2  # real.json holds the episodes themselves; a file without "format" (1) holds only the paths given


@dataclasses.dataclass(frozen=True)
class RealEpisode:
    policy: str
    episode: str  # where it came from: SOURCE:episode id (or CSV line)
    outcomes: dict[str, bool]


def read(sources: tuple[str, ...] | list[str]) -> list[RealEpisode]:
    """Every real episode of ``sources`` (see the module docstring), in order."""
    given = [split_spec(spec)[1] for spec in sources]
    for spellings in same_files(p for p in given if Path(p).exists()).values():
        if len(spellings) > 1:  # one file under two spellings (relative, absolute, a link) would count twice
            raise UserError(f"--real: {' and '.join(map(repr, spellings))} are one file, given twice: drop the "
                            "duplicate")
    out = []
    for spec in sources:
        name, path = split_spec(spec)
        p = Path(path)
        if (p / "dataset.json").is_file():
            got = _from_store(p, name)
        elif (p / "meta" / "info.json").is_file():
            if name is None:
                raise UserError(f"--real {spec}: a LeRobot dataset names no policy; give it as --real NAME={path}")
            got = [RealEpisode(name, f"{path}:episode {i}", {"success": s}) for i, s in lerobot_success(p).items()]
        elif p.suffix.lower() == ".csv" and p.is_file():
            got = _from_csv(p, name)
        else:
            raise UserError(f"--real {spec}: {path} is not an episode store (dataset.json), a LeRobot dataset "
                            "(meta/info.json) or a .csv file")
        if not got:
            raise UserError(f"--real {spec}: no episodes")
        out += got
    seen: dict[tuple[str, str], int] = {}
    for i, e in enumerate(out):  # one episode counted twice would weigh its policy's rate: refused, naming both
        j = seen.setdefault((e.policy, e.episode), i)
        if j != i:
            raise UserError(f"--real: policy {e.policy!r} episode {e.episode.rsplit(':', 1)[-1]!r} is given twice "
                            f"({out[j].episode} and {e.episode}): drop the duplicate")
    return out


def split_spec(spec: str) -> tuple[str | None, str]:
    """``[NAME=]PATH`` -> (NAME or None, PATH)."""
    head, eq, rest = spec.partition("=")
    if eq and head and "/" not in head and rest:
        return head, rest
    return None, spec


def _bool_labels(labels) -> dict[str, bool]:
    if not isinstance(labels, dict):
        return {}
    return {k: bool(v) for k, v in labels.items() if isinstance(v, (bool, np.bool_))}


def _from_store(root: Path, name: str | None) -> list[RealEpisode]:
    from sc3_jax.data.episodes import EpisodeStore

    out = []
    lerobot: dict[str, dict[int, bool]] = {}  # lerobot_root -> its next.success per episode index, read once
    for eid in EpisodeStore(root).episode_ids():
        path = root / eid / "meta.json"
        meta = atomic.read_json(path, "restore it (the episode's metadata)")
        outcomes = _bool_labels(meta.get(LABELS_FIELD))
        if not outcomes and meta.get("source") == "lerobot" and "lerobot_root" in meta:
            src = meta["lerobot_root"]
            if src not in lerobot:
                if not Path(src).is_dir():
                    raise UserError(f"{path}: no boolean {LABELS_FIELD!r} and its LeRobot source {src} (for "
                                    f"{LEROBOT_SUCCESS!r}) is gone: write {LABELS_FIELD} {{criterion: bool}} there")
                lerobot[src] = lerobot_success(Path(src))
            idx = int(meta["episode_index"])
            if idx not in lerobot[src]:
                raise UserError(f"{path}: LeRobot episode {idx} has no rows in {src}")
            outcomes = {"success": lerobot[src][idx]}
        if not outcomes:
            raise UserError(f"{path}: no real outcome: write \"{LABELS_FIELD}\": {{\"success\": true|false, ...}} "
                            "there (or import from a LeRobot dataset with a next.success column)")
        policy = name or meta.get(POLICY_FIELD)
        if not isinstance(policy, str) or not policy:
            raise UserError(f"{path}: no {POLICY_FIELD!r} field naming the policy that ran it: write it there, or "
                            f"give the store as --real NAME={root}")
        out.append(RealEpisode(policy, f"{root}:{eid}", outcomes))
    return out


def lerobot_success(root: Path) -> dict[int, bool]:
    """episode_index -> whether any of its frames has ``next.success`` true, from every data parquet of the LeRobot
    dataset at ``root`` (v2.x: one per episode; v3.0: shared files): the columns are read, no frame is decoded."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        raise UserError(f"{root}/data: no parquet files (not a LeRobot dataset?)")
    out: dict[int, bool] = {}
    for f in files:
        names = pq.read_schema(f).names
        if LEROBOT_SUCCESS not in names or "episode_index" not in names:
            raise UserError(f"{f}: no {LEROBOT_SUCCESS!r} column (have {names}): record success labels, or give "
                            "the outcomes as a CSV (--real FILE.csv)")
        t = pq.read_table(f, columns=["episode_index", LEROBOT_SUCCESS])
        eps = np.asarray(t["episode_index"].to_numpy(zero_copy_only=False)).astype(int)
        col = t[LEROBOT_SUCCESS].combine_chunks()
        if pa.types.is_list(col.type) or pa.types.is_large_list(col.type) or pa.types.is_fixed_size_list(col.type):
            col = col.flatten()  # a [1]-shaped feature stored as a list per row (a plain bool column is LeRobot's)
        ok = np.asarray(col.to_numpy(zero_copy_only=False)).astype(float).reshape(len(eps), -1).any(-1)
        for e in np.unique(eps):
            out[int(e)] = out.get(int(e), False) or bool(ok[eps == e].any())
    return out


def _from_csv(path: Path, name: str | None) -> list[RealEpisode]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: a byte-order mark is not part of a name
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]  # "policy, success" as written by hand
            rows = [(line, dict(zip(header, r))) for line, r in enumerate(reader, start=2)
                    if any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error) as e:  # a binary or damaged file
        raise UserError(f"{path}: not a CSV of UTF-8 text ({' '.join(str(e).split())[:120]}); restore it") from None
    if not rows:
        return []
    cols = header
    if name is None and POLICY_FIELD not in cols:
        raise UserError(f"{path}: no {POLICY_FIELD!r} column (have {cols}): add one, or give --real NAME={path}")
    criteria = [c for c in cols if c not in (POLICY_FIELD, "episode")]
    if not criteria:
        raise UserError(f"{path}: no criterion column besides {POLICY_FIELD!r} / 'episode' (e.g. a 'success' column)")
    out = []
    for line, row in rows:
        outcomes = {}
        for c in criteria:
            v = (row.get(c) or "").strip().lower()
            if v not in TRUE + FALSE:
                raise UserError(f"{path}:{line}: column {c!r} is {row.get(c)!r}; expected true/false, 1/0 or yes/no")
            outcomes[c] = v in TRUE
        policy = name or (row.get(POLICY_FIELD) or "").strip()
        if not policy:
            raise UserError(f"{path}:{line}: empty {POLICY_FIELD!r}")
        out.append(RealEpisode(policy, f"{path}:{(row.get('episode') or '').strip() or line}", outcomes))
    return out


def keep(path: str | Path, given, episodes: list[RealEpisode]) -> None:
    """Write the real outcomes a sweep was given into its store (``path``: its real.json): the ``episodes`` as read
    (in order: the bootstrap's draws follow it), and ``given``, the sources as typed -- a record of where they came
    from, never read again."""
    head = json.dumps({"format": KEPT_FORMAT, "given": list(given)})[:-1]
    rows = ",\n  ".join(json.dumps(dataclasses.asdict(e)) for e in episodes)  # one a line: a diff shows which
    atomic.write_text(path, f'{head},\n "episodes": [\n  {rows}\n ]\n}}\n')


def kept(path: str | Path, out: str | None) -> tuple[list[str], list[RealEpisode]]:
    """The real outcomes a store keeps (``path``: its real.json) and the sources they were given as. A store from
    before they were kept names only paths (``{"real": [...]}``, as typed where the sweep ran): one under the
    sweep's own ``out`` (its sweep.json's) is that file of the store, read from here; any other is refused in one
    line, as nothing in the store says what it held."""
    path = Path(path)
    root, fix = path.parent, "restore it from a copy of the store, or give the real outcomes as --real PATH"
    d = json_object(atomic.read_json(regular_file(path, fix, inside=root), fix), str(path), fix)
    if "format" not in d:
        return _by_path(path, d.get("real"), out, fix)
    if d["format"] != KEPT_FORMAT:
        raise UserError(f"{path}: format {d['format']!r}, this sc3 reads {KEPT_FORMAT}; {fix}")
    given, eps = d.get("given"), d.get("episodes")
    if not (isinstance(given, list) and all(isinstance(g, str) for g in given)):
        raise UserError(f"{path}: given is {given!r}, expected the sources as typed (strings); {fix}")
    if not (isinstance(eps, list) and eps):
        raise UserError(f"{path}: episodes is {str(eps)[:60]!r}, expected the real episodes; {fix}")
    return given, [_kept_episode(e, f"{path}: episode {i}", fix) for i, e in enumerate(eps)]


def _kept_episode(e, where: str, fix: str) -> RealEpisode:
    e = json_object(e, where, fix)
    policy, episode, outcomes = e.get("policy"), e.get("episode"), e.get("outcomes")
    if not (isinstance(policy, str) and policy and isinstance(episode, str)):
        raise UserError(f"{where}: policy {policy!r}, episode {episode!r}: expected a policy name and an episode; "
                        f"{fix}")
    if not (isinstance(outcomes, dict) and outcomes and all(isinstance(v, bool) for v in outcomes.values())):
        raise UserError(f"{where}: outcomes {str(outcomes)[:60]!r}, expected {{criterion: true|false}}; {fix}")
    return RealEpisode(policy, episode, outcomes)


def _by_path(path: Path, sources, out: str | None, fix: str) -> tuple[list[str], list[RealEpisode]]:
    """A real.json from before the outcomes were kept: its sources read from inside the store, or refused."""
    if not (isinstance(sources, list) and sources and all(isinstance(s, str) for s in sources)):
        raise UserError(f"{path}: real is {str(sources)[:60]!r}, expected the sources the sweep was given; {fix}")
    specs = []
    for spec in sources:
        name, p = split_spec(spec)
        rel = _inside(p, out)
        if rel is None or not _within(path.parent / rel, path.parent):
            raise UserError(f"{path}: its real outcomes are named {spec}, outside the store (swept as "
                            f"{out}); a report reads only what its store holds: give them as --real PATH")
        specs.append(f"{name}={path.parent / rel}" if name else str(path.parent / rel))
    return sources, read(specs)


def _inside(p: str, out: str | None) -> str | None:
    """``p`` relative to ``out``, both as the sweep wrote them (one current directory), or None when not under it."""
    if not (isinstance(out, str) and out):
        return None
    p, out = os.path.normpath(p), os.path.normpath(out)
    rel = os.path.relpath(p, out) if os.path.isabs(p) == os.path.isabs(out) else os.pardir
    return None if rel == os.curdir or rel.split(os.sep)[0] == os.pardir else rel


def _within(p: Path, root: Path) -> bool:
    """Whether ``p``, links followed, lies inside ``root`` (a file linked out of the store is not the store's)."""
    base = os.path.realpath(root)
    return os.path.commonpath([base, os.path.realpath(p)]) == base
