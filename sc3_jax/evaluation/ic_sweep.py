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
meta.json "prompt", e.g. "fold the towel", not a table of a benchmark's; none when empty, so the server's default
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

The ``--real`` outcomes are kept in the store, as read, in ``real.json`` beside (not in) ``sweep.json``
(``labels.keep``): the report reads them from there, never from the paths given, which name files where the sweep
ran; they change the report, not the rollouts, so a store is re-reported against other real outcomes (``sc3 report
--real``) without rolling out again.

The rollouts run on the sweep engine (``engine.py``), with this module's ``EpisodesSource``. ``sweep.json`` also
records what the rollouts came from (``engine.with_identity``, for every sweep): the world model's content hash and
training step (``checkpoint.identity``: a path names a workdir that may train on), and the content hash of the scorer
and of each policy where they are files. Resuming against a changed one is refused in one line naming both; a store
written before these were recorded resumes with a note and records none (nothing says what its first rollouts came
from, so no later hash could vouch for them).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.world_model_defaults import Sampler

KIND = "initial_conditions"
REAL_FILE = "real.json"  # the --real outcomes, as read: what the report reads by default


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
    sc3_jax.evaluation.scorers.RolloutView: frames [V, T, H, W, 3], state [T, S], id, instruction) returning
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
    .csv (policy, criterion columns); see sc3_jax/evaluation/labels.py"""
    family: tuple[str, ...] = ()
    """the openpi observation mapping the ws:// policies speak, FAMILY for all of them or NAME=FAMILY for one: native
    (our observation dict as is), droid, libero or aloha (sc3_jax/policies/openpi_mappings.py). A mapped server gets
    each held-out episode's own prompt"""
    benchmark: str | None = None
    """a benchmark whose own policy names --policies may use (its name, e.g. bussing for its zoo, or
    package.module:attr; None: none, only the spellings above)"""
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


class EpisodesSource:
    """What a sweep of held-out episodes hands the engine (``engine.Source``): each episode's initial condition (as
    a mapped openpi server sees it: its own prompt), the lab's ``--scorer`` on each cut a candidate tau makes, and
    the records' episode id and block. No simulator: real outcomes come from labels (``--real``)."""

    outcomes = "outcomes"  # {criterion: bool}
    every_cut = False  # the scorer is the lab's code, called once per cut that some candidate tau makes
    keeps = ("states",)  # the robot state the policy saw

    def __init__(self, cfg: ICSweepConfig, ids: list[str], ics, prompted, prompts: list[str], mapped: set[str],
                 scorer, criteria: tuple[str, ...] | None):
        self.cfg, self.ids, self.ics, self.prompted, self.prompts = cfg, ids, ics, prompted, prompts
        self.mapped, self.scorer, self.criteria = mapped, scorer, criteria
        self.block = {i: b for b, idx in blocks(cfg).items() for i in idx}

    def fields(self, job, seed: int) -> dict:
        return {"episode": self.ids[seed], "block": self.block[seed]}

    def conditions(self, job, spec):
        return (self.prompted if job.name in self.mapped else self.ics).take(np.asarray(job.seeds))

    def score(self, job, b: int, frames: np.ndarray, states: np.ndarray, cuts, keep: int) -> dict:
        from sc3_jax.evaluation.scorers import RolloutView, check_outcomes

        i, rid = job.seeds[b], job.ids()[b]
        by_cut = {}
        for c in cuts:
            n = 1 + c * keep
            view = RolloutView(self.ids[i], frames[:, :n], state=states[:n], instruction=self.prompts[i])
            try:
                got = self.scorer(view)
            except Exception as e:  # the user's code: its traceback, and which rollout it was reading
                e.add_note(f"while --scorer {self.cfg.scorer} scored {rid} ({c} of {max(cuts)} chunks)")
                raise
            by_cut[c] = check_outcomes(self.cfg.scorer, got, rid, self.criteria)
            self.criteria = self.criteria or tuple(sorted(by_cut[c]))
        return by_cut


def run(cfg: ICSweepConfig, named=None) -> Path:
    """Run (or resume) the sweep; returns the store's directory. See the module docstring. ``named``: a benchmark's
    own policy names (``policies.resolve``'s; ``sc3 sweep episodes --benchmark NAME`` passes its)."""
    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout_io
    from sc3_jax.evaluation import engine
    from sc3_jax.evaluation.scorers import load_outcome_scorer
    from sc3_jax.evaluation.world_model_defaults import warn_if_student_off_its_step
    from sc3_jax.policies.openpi_mappings import for_world_model

    _check(cfg)
    served = families(cfg)
    scorer = load_outcome_scorer(cfg.scorer)  # a bad spec is refused before the model loads
    from sc3_jax.evaluation import labels
    # unreadable real outcomes are refused before any rollout, not after hours of them; read once, kept as read
    real = labels.read(cfg.real) if cfg.real else None
    # the store against the model's views and image size before its params load (else a params.npz shape error)
    if Path(cfg.initial_conditions).suffix != ".npz":
        from sc3_jax.data.shape import check_shape

        check_shape(checkpoint.read_config(cfg.world_model), cfg.initial_conditions)
    setup = engine.Setup(cfg.out, cfg.world_model, cfg, named=named, learned_state=cfg.learned_state, pad=True)
    ro, params = engine.load_world_model(setup)  # the sweep's sampler settings (sc3 rollout / diagnose share them)
    wcfg, s = ro.cfg, ro.spec
    warn_if_student_off_its_step(wcfg)
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
    policies = engine.resolve_policies(cfg.policies, named, mappings=mappings, chunk=wcfg.rollout.policy_chunk,
                                       action_space=ro.spec.action_space, num_views=len(wcfg.data.views))
    for p in policies:  # dimensions first: one line naming both sides, before any compile
        try:
            ro.check_policy(p.policy)
        except UserError as e:
            raise UserError(f"--policies {p.spec}: {e} (world model {cfg.world_model})") from None
    config = engine.with_identity(cfg.out, cfg.to_json(ids, [p.name for p in policies]),
                                  engine.identity(cfg.world_model, cfg.scorer, [(p.name, p.spec) for p in policies]))
    source = EpisodesSource(cfg, ids, ics, prompted, prompts, set(mappings), scorer, None)
    # condition i's episode key is (rollout_seed, i): the calibration block's offset is the evaluation block's size
    units = engine.work_units(len(policies), blocks(cfg), ("online",), cfg.batch,
                              {"evaluation": (("online", 0),), "calibration": (("online", cfg.episodes),)})

    def before(results):  # the store, open and locked
        source.criteria = next((tuple(sorted(r["outcomes"])) for r in results.records()), None)  # every rollout's
        if real:
            labels.keep(results.root / REAL_FILE, cfg.real, real)
    return engine.run(setup, config, policies, units, source=source, progress=cfg.progress, model=(ro, params),
                      before=before)
