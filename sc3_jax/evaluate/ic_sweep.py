"""Evaluation without a simulator (issue 33 item 3): rank policies inside a world model from held-out episodes.

    sc3 sweep episodes --data HELDOUT --world-model RUN --policies a=pkg.mod:attr b=ws://HOST:PORT \
              [--family aloha] --scorer pkg.mod:score [--real REAL] --out DIR

Each held-out episode of HELDOUT is one initial condition (its first K frames at the rollout stride from --start, and
the robot state at the last of them: ``rollout_io.load_initial_conditions``, which checks the store's shape against
the model's). Conditions ``0 .. episodes-1`` (in episode-id order) are the evaluation block; the next
``calibration_episodes`` are held out for choosing the early-termination threshold tau (only against real outcomes,
``report_episodes.py``) and never ranked. Every policy acts inside the world model from every condition, closed loop
and untruncated (tau = inf), ``batch`` conditions per world-model call (padded to one shape, so each policy
compiles once); condition i's sampling noise depends only on (rollout_seed, i), so every policy meets the same
draws. The ``--scorer`` (``scorers.load_outcome_scorer``: ``{criterion: bool}`` per rollout) reads the imagined
frames and state of the whole rollout and of each shorter cut a candidate tau would produce.

A ``ws://`` policy is an openpi-protocol server (``policies/openpi_client.py``); ``--family`` picks the openpi
observation mapping it speaks (``policies/openpi_mappings.py``: native, droid, libero, aloha), for every ``ws://``
policy (``FAMILY``) or one (``NAME=FAMILY``). A mapped server gets each condition's own prompt (its episode's
meta.json "prompt", e.g. "fold the towel", not the mapping's bussing table; none when empty, so the server's default
applies), and the mapping's cameras by the world model's view names when those include them (an ALOHA dataset's
cam_high, ...), else in the preset's order.

The store is the simulated sweep's (``results.py``): ``sweep.json`` (this config, with ``"kind":
"initial_conditions"`` and the condition episode ids; a rerun with another config is refused), ``results.jsonl``
(one line per rollout, appended after its arrays are written), ``rollouts/<policy>/<i>_online.npz`` (frames, actions,
states, U). A rerun skips every rollout whose line exists; a killed run redoes at most one batch. Record::

    {"id": "<policy>/<i>_online", "mode": "online", "policy": NAME, "seed": i, "episode": EPISODE_ID,
     "block": "evaluation" | "calibration", "outcomes": {criterion: bool}  (the whole rollout, tau = inf),
     "outcomes_by_cut": {"<chunks kept>": {criterion: bool}}  (each cut some candidate tau makes),
     "u": [N], "u_raw": [N], "num_chunks": N, "frames_per_chunk": l, "stride": s}

``--real`` sources are written to ``real.json`` beside (not in) ``sweep.json``: they change the report, not the
rollouts, so a store is re-reported against other real outcomes without rolling out again.

``sweep.json`` also records what the rollouts came from (:func:`with_identity`, for this sweep and the simulated
benchmark's): the world model's content hash and training step (``checkpoint.identity``: a path names a workdir
that may train on), and the content hash of the scorer and of each policy where they are files. Resuming against
a changed one is refused in one line naming both; a store written before these were recorded resumes with a note
and records none (nothing says what its first rollouts came from, so no later hash could vouch for them).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from sc3_jax import atomic
from sc3_jax.errors import UserError
from sc3_jax.evaluate.world_model_defaults import Sampler
from sc3_jax.evaluate.results import ResultsStore, check_policy_names, rollout_id, terminated_at

KIND = "initial_conditions"
REAL_FILE = "real.json"  # the --real sources the report reads by default


@dataclasses.dataclass(frozen=True, kw_only=True)
class ICSweepConfig(Sampler):
    """Policies of any robot inside the world model from held-out episodes, ranked by a lab's scorer and (--real)
    compared with real outcomes; no simulator. Resumable (rerun the same command); ends with OUT/report/report.md.
    Every field is an option of `sc3 sweep episodes`."""

    # the field keeps its name (sweep.json stores it); the option is the one spelling of a store (commands/flags.py)
    initial_conditions: Annotated[str, tyro.conf.arg(name="data")]
    """initial conditions: an episode store of held-out episodes (or an .npz, as `sc3 rollout` reads): each is one
    initial condition (its first frames and robot state); the first --episodes are ranked, the next
    --calibration-episodes choose tau (against --real only)"""
    world_model: str
    """a training run dir (checkpoints/) or an exported dir (params.npz)"""
    policies: tuple[str, ...]
    """NAME=SPEC ...: package.module:attr (a JaxPolicy / HostPolicy or a factory of one), ws://HOST:PORT (an openpi
    server), zero | random | linear"""
    scorer: str
    """package.module:attr, a function or class called with each imagined rollout (a
    sc3_jax.evaluate.scorers.RolloutView: frames [V, T, H, W, 3], state [T, S], id, instruction) returning
    {criterion: bool}, e.g. {"success": True}; or detector:DIR, a success detector trained on the lab's labelled
    episodes (`sc3 train-detector`)"""
    out: str
    """the results store: results.jsonl, rollouts/, sweep.json and report/ (rerun to resume)"""
    episodes: int = 18
    """evaluation initial conditions per policy (the store's first episodes, in id order)"""
    calibration_episodes: int = 3
    """the next held-out episodes, for choosing tau against --real; never ranked"""
    start: int = 0
    """first frame of the initial context in each episode"""
    task: int = 0
    """task id given to native policies (a mapped ws:// policy gets each episode's own prompt)"""
    real: tuple[str, ...] = ()
    """real outcomes of the same policies, for r / MMRV against the imagined ranking: [NAME=]PATH, an episode store
    (meta.json "policy" and "labels": {criterion: bool}), a LeRobot dataset with next.success (NAME= required) or a
    .csv (policy, criterion columns); see sc3_jax/evaluate/labels.py"""
    family: tuple[str, ...] = ()
    """the openpi observation mapping the ws:// policies speak, FAMILY for all of them or NAME=FAMILY for one: native
    (our observation dict as is), droid, libero or aloha (sc3_jax/policies/openpi_mappings.py). A mapped server gets
    each held-out episode's own prompt"""
    learned_state: bool = True
    """hand the policies the world model's learned robot state where it has one (state_head.npz); --no-learned-state:
    the integrated commands (exact for absolute targets, or velocities of the recorded state)"""
    progress: bool = True
    """progress bar over rollouts (--no-progress: none, for batch logs)"""

    def to_json(self, conditions: list[str], names: list[str]) -> dict:
        """sweep.json: everything that decides the records (not ``real``: the report's; not ``progress``)."""
        # learned_state kept only when off: on, it reads as a store written before it existed (whose models had none)
        d = {k: v for k, v in dataclasses.asdict(self).items() if k != "real" and (k, v) != ("learned_state", True)}
        d.update(kind=KIND, taus=[str(float(t)) for t in self.taus], conditions=conditions, policy_names=names,
                 modes=["online"], seed0=0, calibration_seed0=self.episodes,
                 family=list(self.family) or None)  # None: a store written before --family matches
        return json.loads(json.dumps(d))


def blocks(cfg: ICSweepConfig) -> dict[str, list[int]]:
    """Condition indices per block: evaluation 0..N-1, calibration N..N+C-1."""
    n, c = cfg.episodes, cfg.calibration_episodes
    return {"evaluation": list(range(n)), "calibration": list(range(n, n + c))}


def _check(cfg: ICSweepConfig) -> None:
    if not cfg.policies:
        raise UserError("give the policies to rank, --policies NAME=SPEC ... (SPEC: "
                        "package.module:attr, ws://HOST:PORT, zero | random | linear)")
    if not cfg.scorer:
        raise UserError("give --scorer package.module:attr: a function or class taking a "
                        "RolloutView and returning {criterion: bool} (docs/your_robot.md)")
    if cfg.episodes < 1 or cfg.calibration_episodes < 0 or cfg.batch < 1:
        raise UserError(f"--episodes {cfg.episodes}, --calibration-episodes {cfg.calibration_episodes}, --batch "
                        f"{cfg.batch}: need at least 1 evaluation condition, 0 or more calibration ones, batch >= 1")
    if cfg.tau_units not in ("raw", "normalised"):
        raise UserError(f"--tau-units {cfg.tau_units!r}: 'raw' or 'normalised'")


def families(cfg: ICSweepConfig) -> dict[str, tuple[str, str]]:
    """{policy name: (openpi family, the --family entry that chose it)} of every ``ws://`` policy of
    ``cfg.policies`` (("native", "native") unless --family says): ``FAMILY`` applies to all of them, ``NAME=FAMILY``
    to one (and wins)."""
    from sc3_jax.policies.openpi_mappings import PRESETS
    from sc3_jax.policies.resolve import parse

    served = []
    for spec in cfg.policies:
        try:
            name, body, _ = parse(spec)
        except ValueError as e:
            raise UserError(f"--policies {spec!r}: {e}") from None
        if body.startswith(("ws://", "wss://")):
            served.append(name or body)
    known = ("native", *PRESETS)
    chosen: dict[str | None, tuple[str, str]] = {}  # None: every ws:// policy
    for entry in cfg.family:
        name, eq, fam = entry.rpartition("=")
        who = name if eq else None
        if fam.lower() not in known:
            raise UserError(f"--family {entry}: unknown openpi mapping {fam!r}; expected [NAME=]FAMILY with FAMILY one "
                            f"of {', '.join(known)}")
        if not served:
            raise UserError(f"--family {entry}: applies to ws:// policies (openpi servers); --policies has none")
        if who is not None and who not in served:
            raise UserError(f"--family {entry}: {who!r} is not a ws:// policy of --policies (those: {served})")
        if who in chosen:
            raise UserError(f"--family {entry}: {who or 'every ws:// policy'} already has --family {chosen[who][1]}")
        chosen[who] = (fam.lower(), entry)
    return {n: chosen.get(n, chosen.get(None, ("native", "native"))) for n in served}


def _resolve(specs: tuple[str, ...], chunk: int, mappings: dict, action_space, num_views: int, named=None
             ) -> list[tuple[str, str, object]]:
    """(name, spec, policy) per --policies entry; names unique. ``mappings``: name -> the ObsMapping of a mapped
    ws:// policy; built-in policies (zero, random, linear) act in the world model's ``action_space``."""
    from sc3_jax.policies.resolve import parse, resolve

    out = []
    for spec in specs:
        try:
            name, body, _ = parse(spec)
            r = resolve(spec, chunk, mappings.get(name or body), action_space=action_space, num_views=num_views,
                        named=named)
        except UserError:
            raise
        except (ValueError, TypeError, ImportError, AttributeError, ConnectionError) as e:
            raise UserError(f"--policies {spec!r}: {e}") from None
        out.append((r.name, spec, r.policy))
    names = [n for n, _, _ in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"--policies: the name(s) {dup} occur twice; name each as NAME=SPEC")
    return out


def trained_on(store, ids, train_path: str | Path | None) -> int | None:
    """How many of the episodes ``ids`` of ``store`` are in the world model's training store (``train_path``): all
    when it is the same store, else those imported from the same LeRobot dataset with the same episode_index (other
    stores' episode ids say nothing: two simulator stores both begin at ep000000); None when the training store is
    not here to compare (or unknown: None, a relative data.path, ``checkpoint.training_store``)."""
    if train_path is None:
        return None
    train = Path(train_path)
    if not (train / "dataset.json").exists():
        return None
    if train.resolve() == Path(store.root).resolve():
        return len(ids)

    def key(root: Path, e: str):
        meta = atomic.read_json(root / e / "meta.json")
        return (meta["lerobot_root"], meta["episode_index"]) if "lerobot_root" in meta else None
    seen = {key(train, p.name) for p in train.iterdir() if (p / "meta.json").exists()} - {None}
    return sum(key(Path(store.root), e) in seen for e in ids)


# sweep.json's record of what its rollouts came from (with_identity)
IDENTITY_KEYS = ("world_model_sha256", "world_model_step", "scorer_sha256", "policies_sha256")


def identity(world_model: str | None, scorer: str | None, policies: list[tuple[str, str]]) -> dict:
    """The identity fields of a sweep's ``sweep.json``: the world model's content hash and step
    (``checkpoint.identity``; none when ``world_model`` is None, a sweep that reads no model), the ``scorer``
    spec's hash and each (name, spec) of ``policies`` whose spec names files (:func:`spec_sha256`)."""
    from sc3_jax import checkpoint

    out = {}
    if world_model is not None:
        wm = checkpoint.identity(world_model)
        out.update(world_model_sha256=wm["sha256"], world_model_step=wm["step"])
    scored = spec_sha256(scorer) if scorer else None
    if scored:
        out["scorer_sha256"] = scored
    acting = {name: spec_sha256(spec) for name, spec in policies}
    if any(acting.values()):
        out["policies_sha256"] = {n: h for n, h in acting.items() if h}
    return out


def spec_sha256(spec: str) -> str | None:
    """The content hash of the files a --scorer / --policies spec names: a ``package.module:attr``'s source file, a
    ``detector:DIR`` or ``lerobot:PATH`` directory; None for a server, a built-in or a benchmark's own name (those
    are not files of the user's, or not files at all)."""
    import importlib.util

    from sc3_jax import checkpoint
    from sc3_jax.policies.resolve import parse

    try:
        body = parse(spec)[1]
    except ValueError:
        return None
    for prefix in ("detector:", "lerobot:"):
        if body.startswith(prefix):
            root = Path(body[len(prefix):])
            files = [root] if root.is_file() else sorted(f for f in root.rglob("*") if f.is_file())
            return checkpoint.files_sha256([(str(f.relative_to(root)) if f != root else f.name, f) for f in files]) \
                if files else None
    if "://" in body or ":" not in body:
        return None
    try:  # imported already (the spec was resolved): its module's file
        found = importlib.util.find_spec(body.partition(":")[0])
    except (ImportError, ValueError):
        return None
    origin = Path(found.origin) if found is not None and found.origin else None
    return checkpoint.files_sha256([(origin.name, origin)]) if origin is not None and origin.is_file() else None


def with_identity(out: str | Path, config: dict, ident: dict) -> dict:
    """``config`` (a sweep.json to be) with the identity fields ``ident`` (:func:`identity`), after checking them
    against the store ``out`` already holds: a resume against another world model (its workdir trained on, or
    another export at the same path), scorer or policy file is refused in one line naming the old and the new.
    A store whose rollouts were recorded before sweep.json named their model is accepted with a note and
    ``config`` returned as it is: it records nothing new (nothing says what its first rollouts came from)."""
    from sc3_jax.evaluate.results import ResultsStore

    path = Path(out) / "sweep.json"
    if not path.is_file() or not ResultsStore(out)._holds_results():  # a new store (or one with no rollout yet)
        return {**config, **ident}
    old = atomic.read_json(path, "restore it from a copy, or use another --out")
    if not isinstance(old, dict):
        return {**config, **ident}  # not a sweep's record: the store refuses it in its own line
    if "world_model_sha256" not in old:
        print(f"note: {path} predates recording the world model's content hash: resumed as it was, with none "
              "recorded (a changed model at the same path is not detected; a new --out records it)")
        return config

    def model(d):
        step, sha = d.get("world_model_step"), str(d.get("world_model_sha256"))[:16]
        return f"sha256 {sha}, an export" if step is None else f"step {step}, sha256 {sha}"
    if ident.get("world_model_sha256") not in (None, old["world_model_sha256"]):
        raise UserError(f"{out} holds rollouts of world model {old.get('world_model')} ({model(old)}); "
                        f"{config.get('world_model')} is now {model(ident)}: resuming would rank two models' rollouts "
                        "together; give the model it was swept with, or use another --out")
    if old.get("scorer_sha256") != ident.get("scorer_sha256"):
        raise UserError(f"{out} was scored by --scorer {old.get('scorer')} with sha256 "
                        f"{str(old.get('scorer_sha256'))[:16]}; its files are now sha256 "
                        f"{str(ident.get('scorer_sha256'))[:16]}: resuming would mix two scorers' outcomes; restore "
                        "it, or use another --out")
    was, now = old.get("policies_sha256") or {}, ident.get("policies_sha256") or {}
    changed = sorted(n for n in set(was) & set(now) if was[n] != now[n])
    if changed:
        n = changed[0]
        raise UserError(f"{out} holds rollouts of policy {n!r} with sha256 {was[n][:16]}; its files are now sha256 "
                        f"{now[n][:16]}: resuming would rank two versions of it together; restore it, name the new "
                        "one otherwise, or use another --out")
    return {**config, **ident}


def cut(u: np.ndarray, tau: float) -> int:
    """Chunks a rollout with U_chunk ``u`` [N] keeps under threshold ``tau``: those before the first with U > tau
    (``calibrate.cut``'s rule, which the report applies to the stored ``u`` / ``u_raw``)."""
    first = int(terminated_at(np.asarray(u)[None], tau)[0])
    return len(u) if first < 0 else first


def _mesh(batch: int):
    """A mesh over as many local devices as divide the batch: every device busy, no batch padded beyond it."""
    import jax

    from sc3_jax import sharding
    from sc3_jax.config import MeshConfig

    devices = jax.local_devices()
    d = max(k for k in range(1, min(batch, len(devices)) + 1) if batch % k == 0)
    return sharding.make_mesh(MeshConfig(-1, 1, 1), devices[:d])


def run(cfg: ICSweepConfig, named=None) -> Path:
    """Run (or resume) the sweep; returns the store's directory. See the module docstring. ``named``: a benchmark's
    own policy names (``policies.resolve``'s; ``sc3 sweep episodes`` passes the simulated benchmark's zoo)."""
    import jax
    from tqdm import tqdm

    from sc3_jax import checkpoint, rollout, rollout_io, state_head
    from sc3_jax.evaluate.scorers import RolloutView, check_outcomes, load_outcome_scorer
    from sc3_jax.evaluate.world_model_defaults import evaluation_config, warn_if_student_off_its_step
    from sc3_jax.policies.openpi_mappings import for_world_model

    _check(cfg)
    served = families(cfg)
    scorer = load_outcome_scorer(cfg.scorer)  # a bad spec is refused before the model loads
    if cfg.real:
        from sc3_jax.evaluate import labels
        labels.read(cfg.real)  # unreadable real outcomes are refused before any rollout, not after hours of them
    wcfg, stats, params = checkpoint.load(cfg.world_model)
    wcfg = evaluation_config(wcfg, cfg)  # the sweep's sampler settings (sc3 rollout / diagnose share them)
    warn_if_student_off_its_step(wcfg)
    fps = checkpoint.read_robot(cfg.world_model, wcfg).fps  # the frame rate the model was trained at (config.json)
    ro = rollout.Rollout(wcfg, stats, mesh=_mesh(cfg.batch), data_fps=fps,
                         head=state_head.load(cfg.world_model) if cfg.learned_state else None)
    s = ro.spec
    want = cfg.episodes + cfg.calibration_episodes
    ids, ics, store = rollout_io.load_initial_conditions(cfg.initial_conditions, wcfg, s, want, cfg.start, cfg.task)
    if len(ids) < want:
        raise UserError(f"--data {cfg.initial_conditions}: {len(ids)} episodes, the sweep needs "
                        f"--episodes {cfg.episodes} + --calibration-episodes {cfg.calibration_episodes} = {want}: "
                        "lower them or give more held-out episodes")
    seen = trained_on(store, ids, checkpoint.training_store(cfg.world_model, wcfg)) if store else None
    if seen:
        print(f"warning: {seen} of the {len(ids)} initial conditions are episodes the world model trained on "
              f"(its data.path {wcfg.data.path}): they rank what it has seen; give held-out episodes (e.g. `sc3 data "
              "import-lerobot ... --episodes 20:` beside a training import of `--episodes 0:20`)")
    prompts = [atomic.read_json(store.root / e / "meta.json").get("prompt", "") if store else "" for e in ids]
    # a mapped (openpi) server reads a prompt, not our task id: condition i's task id indexes its own prompt
    table = list(dict.fromkeys(prompts))
    prompted = ics._replace(task=np.asarray([table.index(p) for p in prompts], np.int32))
    mappings = {}  # policy name -> the openpi mapping its server speaks (native ones: none)
    for n, (fam, entry) in served.items():
        m = for_world_model(fam, tuple(wcfg.data.views), table, f"--family {entry}")
        if m is not None:
            mappings[n] = m
    policies = _resolve(cfg.policies, wcfg.rollout.policy_chunk, mappings, stats.action_space, len(wcfg.data.views),
                        named)
    check_policy_names([n for n, _, _ in policies])
    for name, spec, policy in policies:  # dimensions first: one line naming both sides, before any compile
        try:
            ro.check_policy(policy)
        except UserError as e:
            raise UserError(f"--policies {spec}: {e} (world model {cfg.world_model})") from None
    config = with_identity(cfg.out, cfg.to_json(ids, [n for n, _, _ in policies]),
                           identity(cfg.world_model, cfg.scorer, [(n, spec) for n, spec, _ in policies]))
    results = ResultsStore(cfg.out, config, lock=True)
    try:
        if cfg.real:
            atomic.write_json(results.root / REAL_FILE, {"real": list(cfg.real)})
        done = results.done()
        criteria = next((tuple(sorted(r["outcomes"])) for r in results.records()), None)
        taus = [float(t) for t in cfg.taus] + [math.inf]
        units = [(name, spec, policy, block, idx[g:g + cfg.batch]) for name, spec, policy in policies
                 for block, idx in blocks(cfg).items() for g in range(0, len(idx), cfg.batch)]
        total = len(policies) * want
        bar = tqdm(total=total, initial=len(done), desc="sweep", unit="rollout", disable=not cfg.progress)
        t0, ran = time.time(), 0
        for name, spec, policy, block, idx in units:
            rids = [rollout_id(name, i, "online") for i in idx]
            if all(r in done for r in rids):
                continue
            sel = np.asarray(idx + [idx[-1]] * (cfg.batch - len(idx)))  # one shape for every batch: one compile
            sub = (prompted if name in mappings else ics).take(sel)
            keys = np.asarray(rollout.episode_keys(cfg.rollout_seed, len(sel), start=idx[0]))  # condition i: (seed, i)
            try:
                out = rollout_io.closed_loop(ro, params, policy, sub, keys, math.inf, len(sel), False)
            except UserError as e:  # a host policy's chunks are checked as they arrive
                raise UserError(f"--policies {spec}: {e} (world model {cfg.world_model})") from None
            except Exception as e:  # the policy's code (or its server): its traceback, and which policy it was
                e.add_note(f"while policy {name!r} ({spec}) acted in rollouts {rids[0]} .. {rids[-1]}")
                raise
            recs = []
            for b, (i, rid) in enumerate(zip(idx, rids)):
                frames = np.concatenate([out["initial_frames"][b][:, -1:], out["frames"][b]], 1)  # [V, 1 + N*l, ...]
                # what the policy saw: the robot's learned state where the model has one, else the commands'
                learned = "robot_states" in out
                states = np.concatenate([np.asarray((sub.robot if learned else sub.state)[b], np.float32)[None],
                                         out["robot_states" if learned else "states"][b]], 0)
                u, u_raw = out["u"][b], out["u_raw"][b]
                cuts = sorted({cut(u if cfg.tau_units == "normalised" else u_raw, t) for t in taus})
                by_cut = {}
                for c in cuts:
                    n = 1 + c * s.keep
                    view = RolloutView(ids[i], frames[:, :n], state=states[:n], instruction=prompts[i])
                    try:
                        got = scorer(view)
                    except Exception as e:  # the user's code: its traceback, and which rollout it was reading
                        e.add_note(f"while --scorer {cfg.scorer} scored {rid} ({c} of {s.num_chunks} chunks)")
                        raise
                    by_cut[str(c)] = check_outcomes(cfg.scorer, got, rid, criteria)
                    criteria = criteria or tuple(sorted(by_cut[str(c)]))
                results.save_arrays(rid, frames=frames, actions=out["actions"][b], states=states[1:], u=u, u_raw=u_raw)
                recs.append({"id": rid, "mode": "online", "policy": name, "seed": i, "episode": ids[i], "block": block,
                             "outcomes": by_cut[str(s.num_chunks)], "outcomes_by_cut": by_cut, "u": u.tolist(),
                             "u_raw": u_raw.tolist(), "num_chunks": s.num_chunks, "frames_per_chunk": s.keep,
                             "stride": s.stride})
            results.append(recs)
            ran += len(recs)
            bar.update(len(recs))
        bar.close()
        for name, _, policy in policies:
            if name in served:  # our side of the connection to an openpi server
                policy.close()
        atomic.write_json(results.root / "timing.json", {
            "seconds_last_run": time.time() - t0, "rollouts_run": {"online": ran},
            "devices": [str(d) for d in jax.local_devices()]})
        return results.root
    finally:
        results.close()  # the lock: another sweep may take the store
