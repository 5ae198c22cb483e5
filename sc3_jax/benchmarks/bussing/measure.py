"""Measurements quoted in docs/sim.md: render time, demos/hour, share of pixels that change per view, expert success
per task and per knob. ``sc3 sim measure [--episodes N]`` prints them (``measure_all``) and says what each means.
"""
from __future__ import annotations

import tempfile
import time

import numpy as np

from .criteria import success_rates
from .env import BussingEnv
from .expert import ExpertKnobs, run_expert_episode

KNOBS = {"clean": ExpertKnobs(), "grasp_noise=0.05": ExpertKnobs(grasp_noise=0.05),
         "release_noise=0.1": ExpertKnobs(release_noise=0.1),
         "wrong_destination_prob=0.5": ExpertKnobs(wrong_destination_prob=0.5),
         "action_noise=0.015": ExpertKnobs(action_noise=0.015)}


def render_ms(image_size=(64, 64), n: int = 200) -> float:
    """Milliseconds to render all three views once."""
    env = BussingEnv(image_size=image_size)
    env.reset(0)
    env.render()
    t = time.perf_counter()
    for _ in range(n):
        env.render()
    ms = (time.perf_counter() - t) / n * 1000
    env.close()
    return ms


def changed_pixel_fraction(episodes: int = 5, image_size=(64, 64), threshold: int = 20) -> dict[str, dict]:
    """Per view, over expert episodes (mean over episodes), pixels whose colour differs by more than ``threshold``
    (any channel) from the episode's first frame: ``ever`` = share of pixels that change at some time;
    ``per_frame`` = mean share changed in a frame; ``step`` = mean share changed between consecutive frames."""
    env = BussingEnv(image_size=image_size)
    out = {v: {"ever": [], "per_frame": [], "step": []} for v in env.views}
    for s in range(episodes):
        r = run_expert_episode(env, 20_000_000 + s, "bussing", record=True)
        for v in env.views:
            f = r.frames[v].astype(np.int16)
            diff = np.abs(f - f[:1]).max(-1) > threshold
            out[v]["ever"].append(float(np.mean(np.any(diff, axis=0))))
            out[v]["per_frame"].append(float(np.mean(diff)))
            out[v]["step"].append(float(np.mean(np.abs(np.diff(f, axis=0)).max(-1) > threshold)))
    env.close()
    return {v: {k: round(float(np.mean(x)), 4) for k, x in d.items()} for v, d in out.items()}


def demos_per_hour(n: int = 10) -> dict:
    from .demos import generate_demos
    with tempfile.TemporaryDirectory() as d:
        s = generate_demos(d, n, seed=77, progress=False)
    return {"demos_per_hour": s["demos_per_hour"], "steps_per_demo": s["steps"] / max(s["written"], 1)}


def expert_rates(episodes: int = 20) -> dict:
    env = BussingEnv(render=False)
    res = {}
    for task in ("bussing", "reverse"):
        outs = []
        for s in range(episodes):
            outs += run_expert_episode(env, 30_000_000 + s, task, ExpertKnobs(), record=False).outcomes
        res[f"expert/{task}"] = success_rates(outs)
    for name, k in KNOBS.items():
        if name == "clean":
            continue
        outs = []
        for s in range(episodes):
            outs += run_expert_episode(env, 30_000_000 + s, "bussing", k, record=False).outcomes
        res[f"knob/{name}"] = success_rates(outs)
    return res


def measure_all(episodes: int = 20) -> dict:
    """Every measurement above, as quoted in docs/sim.md; ``episodes`` per expert task and per knob."""
    res = {"render_ms_per_3view_frame_64x64": render_ms((64, 64), 200)}
    res["render_ms_per_3view_frame_480x640"] = render_ms((480, 640), 30)
    res["changed_pixel_fraction"] = changed_pixel_fraction()
    res.update(demos_per_hour())
    res.update(expert_rates(episodes))
    return res
