"""``sc3 sweep [--OPTION VALUE ...]``: policies x initial conditions, real and inside the world model, then the
report. With ``--initial-conditions STORE --scorer module:attr``: no simulator -- the policies act inside the world
model from a store's held-out episodes, are ranked, and (``--real``) compared with real outcomes
(sc3_jax/evaluate/ic_sweep.py, docs/your_robot.md)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from sc3_jax.commands import parse
from sc3_jax.errors import UserError
from sc3_jax.benchmarks.bussing.sweep import SweepConfig

SUMMARY = "policies x initial conditions, real and inside the world model, then the report"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args(SweepConfig):
    """Evaluate policies in the simulator and inside the world model, or (--initial-conditions) inside the world
    model only, from held-out episodes of any robot; resumable (rerun the same command). Ends with
    OUT/report/report.md. Every field is an option of `sc3 sweep` (--field-name VALUE)."""

    initial_conditions: str | None = None
    """no simulator: an episode store of held-out episodes (or an .npz, as `sc3 rollout` reads): each is one initial
    condition (its first frames and robot state); the first --episodes are ranked, the next --calibration-episodes
    choose tau (against --real only). Needs --world-model, --policies NAME=SPEC ... and --scorer. The simulator's
    options (--tasks, --seed0, --ceiling-*, --modes, --degradations, --workers) do not apply; --episode-seconds
    applies (its default, 12 s, is the benchmark's: give your task's horizon)"""
    scorer: str | None = None
    """with --initial-conditions: package.module:attr, a function or class called with each imagined rollout (a
    sc3_jax.evaluate.scorers.RolloutView: frames [V, T, H, W, 3], state [T, S], id, instruction) returning
    {criterion: bool}, e.g. {"success": True}"""
    real: tuple[str, ...] = ()
    """with --initial-conditions: real outcomes of the same policies, for r / MMRV against the imagined ranking:
    [NAME=]PATH, an episode store (meta.json "policy" and "labels": {criterion: bool}), a LeRobot dataset with
    next.success (NAME= required) or a .csv (policy, criterion columns); see sc3_jax/evaluate/labels.py"""
    start: int = 0
    """with --initial-conditions: first frame of the initial context in each episode"""
    family: tuple[str, ...] = ()
    """with --initial-conditions: the openpi observation mapping the ws:// policies speak, FAMILY for all of them or
    NAME=FAMILY for one: native (our observation dict as is; the default), droid, libero or aloha (openpi's layouts,
    sc3_jax/policies/openpi_mappings.py; aloha: cam_high, cam_low, cam_left_wrist, cam_right_wrist CHW, 14-D state
    and actions). A mapped server gets each held-out episode's own prompt"""


# SweepConfig fields that mean something only with a simulator: refused with --initial-conditions when set
SIMULATOR_ONLY = ("perception", "state_reader", "real_from", "shard")


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "sweep")
    if a.initial_conditions is not None:
        return _without_simulator(a)
    for name, value in (("--scorer", a.scorer), ("--real", a.real), ("--family", a.family)):
        if value:
            raise UserError(f"{name} applies to a sweep without simulator: add --initial-conditions STORE")
    cfg = SweepConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(SweepConfig)})
    from sc3_jax.evaluate import report
    from sc3_jax.benchmarks.bussing import sweep

    out = sweep.run_sweep(cfg)
    if out != Path(cfg.out):  # one shard of several: the report reads them all once every shard has finished
        print(f"shard done: {out}; once every shard has finished: sc3 report {cfg.out}")
        return 0
    try:
        from sc3_jax.benchmarks.bussing.hooks import object_pixels
        md = report.render(out, out / "report", scene=object_pixels)
    except UserError as e:  # e.g. --modes online alone: the rollouts are kept, the report waits for real ones
        print(f"rollouts: {out}; no report: {e}")
        return 0
    t = json.loads((out / "report" / "report.json").read_text())
    title, header, rows = next(x for x in report.tables(t) if x[0].startswith("Faithfulness, end to end"))
    print(f"## {title}\n\n| " + " | ".join(header) + " |\n" + "".join("| " + " | ".join(r) + " |\n" for r in rows))
    print("\n".join(report.verdict(t) + t.get("warnings", [])))
    print(f"report: {md} (and report.html, report.json, correlation.png)")
    return 0


def _without_simulator(a: Args) -> int:
    bad = [f"--{k.replace('_', '-')}" for k in SIMULATOR_ONLY if getattr(a, k) is not None]
    if bad:
        raise UserError(f"{', '.join(bad)}: simulator options; a sweep with --initial-conditions has no simulator "
                        "(drop them)")
    from sc3_jax.evaluate import ic_ranking, ic_sweep

    cfg = ic_sweep.ICSweepConfig(
        initial_conditions=a.initial_conditions, world_model=a.world_model, policies=a.policies, scorer=a.scorer,
        out=a.out, episodes=a.episodes, calibration_episodes=a.calibration_episodes, batch=a.batch,
        rollout_seed=a.rollout_seed, episode_seconds=a.episode_seconds, sample_steps=a.sample_steps,
        inverse_steps=a.inverse_steps, taus=a.taus, tau_units=a.tau_units, start=a.start, real=a.real,
        family=a.family, progress=a.progress)
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    out = ic_sweep.run(cfg, named=named_policy)
    md = ic_ranking.render(out, out / "report", cfg.real or None)
    t = json.loads((out / "report" / "report.json").read_text())
    print(f"sweep: {len(cfg.policies)} policies x {cfg.episodes} held-out initial conditions (+ "
          f"{cfg.calibration_episodes} for tau) of {cfg.initial_conditions}, closed loop inside {cfg.world_model}, "
          f"scored by {cfg.scorer}; records: {out}/results.jsonl")
    served = ic_sweep.families(cfg)
    if served:
        print("openpi policy servers (ws://) and the observation mapping each speaks: "
              + ", ".join(f"{n} ({fam})" for n, (fam, _) in served.items()))
    print("\n".join(ic_ranking.summary(t)))
    print(f"report: {md} (and report.json)")
    return 0
