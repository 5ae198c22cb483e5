"""A sweep store's success rates as ``lerobot-eval`` writes them (``eval_info.json``), so a lab's dashboards that read
LeRobot's file read ours: one file per (mode, policy), ``OUT/<mode>/<policy>/eval_info.json`` (mode "online": the
policy imagined inside the world model; "real": the simulator's or the lab's episodes, where the store has them).

Shape (lerobot 0.6.1's ``eval_policy_all``), plus a Wilson 95% interval beside each rate (``pc_success_ci95``, in
percent as ``pc_success``; ``stats.interval.wilson``) and an ``sc3`` entry saying what was counted::

    {"per_task": [{"task_group": G, "task_id": T, "metrics": {"sum_rewards": [...], "max_rewards": [...],
                   "successes": [...], "video_paths": [], "predicted_video_paths": [], "episodes": [...],
                   "pc_success": P, "pc_success_ci95": [lo, hi], "n_episodes": n}}, ...],
     "per_group": {G: {"avg_sum_reward", "avg_max_reward", "pc_success", "pc_success_ci95", "n_episodes",
                       "video_paths", "predicted_video_paths"}},
     "overall": {... as a group, "eval_s", "eval_ep_s"},
     "sc3": {"policy", "mode", "criterion", "block", "store", "interval"}}

An episode's success is its record's ``outcomes[criterion]`` (``sc3 sweep episodes`` / ``so101``), or for a record
of per-object outcomes (``sc3 sweep bench``) every object passing ``criterion`` (by default the benchmark's last,
cumulative one: ``results.criteria_order``, e.g. "placing"); its reward is 1.0
on success, else 0 (what the gymnasium env, ``gym_env.py``, pays). Tasks: a record's ``split`` / ``task`` where it
has them (the bussing benchmark's), else one task, the store's benchmark. Only the ``block`` (evaluation by default)
counts: calibration episodes chose tau and are not ranked."""
from __future__ import annotations

import math
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import ResultsStore, criteria_order, seed_blocks
from sc3_jax.core.safe_names import join_inside
from sc3_jax.stats.interval import wilson

FILE = "eval_info.json"
MODES = ("online", "real")


def _success(r: dict, criterion: str, where: str) -> bool:
    if isinstance(r.get("outcomes"), dict):
        got = r["outcomes"]
        if criterion not in got:
            raise UserError(f"{where}: record {r['id']} has criteria {sorted(got)}, not {criterion!r}; pass one of "
                            "them")
        return bool(got[criterion])
    objects = r.get("objects")
    if isinstance(objects, list) and objects:
        if any(criterion not in o for o in objects):
            have = sorted(k for k, v in objects[0].items() if isinstance(v, bool))
            raise UserError(f"{where}: record {r['id']}'s objects have criteria {have}, not {criterion!r}; pass one "
                            "of them")
        return all(bool(o[criterion]) for o in objects)
    raise UserError(f"{where}: record {r['id']} has no outcomes to count (neither 'outcomes' nor 'objects')")


def _block(r: dict, blocks: dict) -> str:
    """A record's block: its own field (``ic_sweep``'s), else the block its seed is in (the bussing sweep's)."""
    if "block" in r:
        return r["block"]
    return next((b for b, seeds in blocks.items() if r.get("seed") in seeds), "evaluation")


def _rate(successes: list[bool]) -> dict:
    n, k = len(successes), int(sum(successes))
    ci = wilson(k, n)
    pc = 100.0 * k / n if n else math.nan
    return {"pc_success": pc, "pc_success_ci95": [100.0 * ci["lo"], 100.0 * ci["hi"]], "n_episodes": n}


def _aggregate(successes: list[bool]) -> dict:
    rewards = [float(s) for s in successes]
    mean = sum(rewards) / len(rewards) if rewards else math.nan
    return {"avg_sum_reward": mean, "avg_max_reward": mean, **_rate(successes),
            "video_paths": [], "predicted_video_paths": []}


def eval_info(records: list[dict], policy: str, mode: str = "online", criterion: str = "success",
              block: str = "evaluation", suite: str = "sc3", blocks: dict | None = None,
              eval_s: float | None = None, where: str = "eval_info") -> dict:
    """``lerobot-eval``'s ``eval_info.json`` dict for ``policy``'s ``mode`` records of ``block`` (module docstring).
    ``blocks``: seed blocks (``results.seed_blocks``) for records without a ``block`` field."""
    blocks = blocks or {}
    mine = [r for r in records if r.get("policy") == policy and r.get("mode") == mode
            and _block(r, blocks) == block]
    if not mine:
        raise UserError(f"{where}: no {mode} records of policy {policy!r} in the {block} block")
    tasks: dict[tuple, list] = {}
    for r in sorted(mine, key=lambda r: (str(r.get("split", "")), str(r.get("task", "")), r.get("seed", 0))):
        key = (r.get("split") or suite, r.get("task") if r.get("task") is not None else 0)
        tasks.setdefault(key, []).append(r)
    per_task, groups = [], {}
    for (group, task), rs in tasks.items():
        s = [_success(r, criterion, where) for r in rs]
        groups.setdefault(group, []).extend(s)
        per_task.append({"task_group": group, "task_id": task, "metrics": {
            "sum_rewards": [float(x) for x in s], "max_rewards": [float(x) for x in s], "successes": s,
            "video_paths": [], "predicted_video_paths": [],
            "episodes": [r.get("episode", r["id"]) for r in rs], **_rate(s)}})
    every = [x for s in groups.values() for x in s]
    overall = _aggregate(every)
    overall["eval_s"] = eval_s
    overall["eval_ep_s"] = None if eval_s is None else eval_s / len(every)
    return {"per_task": per_task, "per_group": {g: _aggregate(s) for g, s in groups.items()}, "overall": overall,
            "sc3": {"policy": policy, "mode": mode, "criterion": criterion, "block": block,
                    "interval": "Wilson score, 95%"}}


def write(results: str | Path, out: str | Path | None = None, criterion: str | None = None,
          block: str = "evaluation") -> list[Path]:
    """Write ``OUT/<mode>/<policy>/eval_info.json`` for every policy and mode of the store ``results`` (``out``
    None: ``RESULTS/report/eval_info``); returns the files written. ``criterion`` None: "success" for a store of
    ``{criterion: bool}`` outcomes, the last criterion for one of per-object outcomes."""
    store = ResultsStore(results)
    records = store.records()
    out = Path(out) if out is not None else store.root / "report" / "eval_info"
    cfg = store.config()
    if criterion is None:
        per_object = criteria_order(cfg, records)
        criterion = per_object[-1] if per_object else "success"
    try:
        blocks = seed_blocks(cfg)
    except (KeyError, TypeError):
        blocks = {}
    bench = (atomic.read_json(store.root / "benchmark.json").get("benchmark")
             if (store.root / "benchmark.json").is_file() else None)
    timing = store.root / "timing.json"
    seconds = atomic.read_json(timing).get("seconds_last_run") if timing.is_file() else None
    written = []
    for mode in MODES:
        for policy in sorted({r["policy"] for r in records if r.get("mode") == mode}):
            if not any(r.get("policy") == policy and r.get("mode") == mode and _block(r, blocks) == block
                       for r in records):
                continue
            info = eval_info(records, policy, mode, criterion, block, suite=bench or "sc3", blocks=blocks,
                             eval_s=seconds if mode == "online" else None, where=str(store.root))
            info["sc3"]["store"] = str(store.root)
            path = join_inside(out, mode, policy, FILE)
            atomic.write_json(path, info)
            written.append(path)
    if not written:
        raise UserError(f"{store.root}: no {block} records to write an eval_info.json from")
    return written
