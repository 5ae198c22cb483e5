"""A policy's real outcomes from LeRobot's own evaluation: the ``eval_info.json`` that the real ``lerobot-eval
--env.type=sc3_so101 --seed=0`` writes (``plugins/lerobot_env_sc3``), read by ``sc3 sweep so101 --lerobot-eval
NAME=EVAL_INFO`` as that policy's real outcomes instead of running it in the simulator here.

With ``--seed=0``, LeRobot's episode i starts from the sweep's condition i (``vec_env``: seed i resets the simulator
at the sweep's ``EVAL_SEED0 + i``), and it ends at ``--env.episode_length`` steps (default: the sweep's 10 s). Neither
is written in the file, so the docs' command sets both. The file is kept in the store, ``OUT/lerobot_eval/NAME/
eval_info.json``, beside ``report/``: a lab's dashboard reads the rate the report ranks against.
"""
from __future__ import annotations

import json
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError

ENV_TYPE = "sc3_so101"  # the plugin's --env.type: the task group its eval_info.json names
KEPT = "lerobot_eval"  # OUT/KEPT/NAME/eval_info.json


def parse(spec: str) -> tuple[str, Path]:
    """``NAME=EVAL_INFO`` -> (the policy's name, the file)."""
    name, sep, path = spec.partition("=")
    if not (sep and name and path):
        raise UserError(f"--lerobot-eval {spec!r}: NAME=EVAL_INFO (a policy's name, the eval_info.json that "
                        f"lerobot-eval --env.type={ENV_TYPE} wrote for it)")
    return name, Path(path)


def successes(path: Path, episodes: int) -> tuple[list[bool], dict]:
    """(the first ``episodes`` episodes' successes, the whole eval_info) of ``path``; a file that is not
    ``lerobot-eval --env.type=sc3_so101``'s, or has fewer episodes, is one line."""
    try:
        info = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"--lerobot-eval {path}: cannot read it as JSON ({type(e).__name__})") from None
    tasks = info.get("per_task") if isinstance(info, dict) else None
    ours = [t for t in tasks if isinstance(t, dict) and t.get("task_group") == ENV_TYPE] if isinstance(tasks, list) \
        else []
    if len(ours) != 1:
        groups = sorted({str(t.get("task_group")) for t in tasks if isinstance(t, dict)}) if isinstance(tasks, list) \
            else []
        raise UserError(f"--lerobot-eval {path}: not the eval_info.json of one lerobot-eval --env.type={ENV_TYPE} "
                        f"(its per_task names {groups or 'nothing'})")
    done = (ours[0].get("metrics") or {}).get("successes")
    if not isinstance(done, list) or not all(isinstance(x, bool) for x in done):
        raise UserError(f"--lerobot-eval {path}: its per_task metrics hold no list of successes")
    if len(done) < episodes:
        raise UserError(f"--lerobot-eval {path}: {len(done)} episodes, the sweep's --episodes {episodes} needs as "
                        f"many (lerobot-eval --eval.n_episodes={episodes} --seed=0)")
    return done[:episodes], info


def keep(out: Path, name: str, info: dict) -> Path:
    """``info`` written to ``OUT/lerobot_eval/NAME/eval_info.json`` (NAME a store folder's name, checked by the
    sweep's policy resolution); returns the path."""
    from sc3_jax.core.safe_names import join_inside

    path = join_inside(Path(out) / KEPT, name, "eval_info.json")
    atomic.write_json(path, info)
    return path
