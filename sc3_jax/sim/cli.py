"""``sc3 sim ...``: demonstrations, policy evaluation, zoo training/listing.

    sc3 sim demos --out DIR --episodes N [--seed S] [--grasp-noise M] [--release-noise M]
                  [--wrong-destination-prob P] [--action-noise M] [--image-size H W] [--control-hz 20|10]
                  [--policy BUSSING_ZOO_POLICY] [--allow-swap-all]
    sc3 sim demos-stats --store DIR [DIR ...]       what a demo store holds (tasks, sources, objects swapped)
    sc3 sim eval --policy NAME --task bussing|reverse --episodes 36 --out DIR [--no-videos]
    sc3 sim zoo-train [--workdir /tmp/sc3_zoo]
    sc3 sim zoo-eval --out DIR [--episodes 36] [--no-videos] [--policies NAME ...]   (resumable)
    sc3 sim zoo-list

Wiring into the main CLI is one line: ``from sc3_jax.sim.cli import main as sim_main; sim_main(argv)``.
"""
from __future__ import annotations

import argparse
import json


def demos(out: str, episodes: int = 100, seed: int = 0, grasp_noise: float = 0.0, release_noise: float = 0.0,
          wrong_destination_prob: float = 0.0, action_noise: float = 0.0, image_size: tuple[int, int] = (64, 64),
          control_hz: int = 20, n_objects: int = 3, progress: bool = True, policy: str | None = None,
          allow_swap_all: bool = False) -> dict:
    from .demos import generate_demos
    from .expert import ExpertKnobs
    knobs = ExpertKnobs(grasp_noise, release_noise, wrong_destination_prob, action_noise,
                        never_swap_all=not allow_swap_all)
    return generate_demos(out, episodes, seed, knobs, tuple(image_size), control_hz, n_objects, progress=progress,
                          policy=policy)


def eval(policy: str, task: str = "bussing", episodes: int = 36, out: str | None = None, videos: bool = True,
         image_size: tuple[int, int] = (64, 64), progress: bool = True) -> dict:  # noqa: A001 (CLI verb)
    from ..policies.resolve import resolve  # any spelling; a command may import above the simulator
    from .policy_eval import evaluate_policy
    return evaluate_policy(resolve(policy).policy, task, episodes, out, image_size=tuple(image_size), videos=videos,
                           progress=progress)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="sc3 sim", description="MuJoCo table-bussing benchmark")
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demos", help="write scripted-expert bussing demonstrations (episode store format)")
    d.add_argument("--out", required=True)
    d.add_argument("--episodes", type=int, default=100)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--grasp-noise", type=float, default=0.0)
    d.add_argument("--release-noise", type=float, default=0.0)
    d.add_argument("--wrong-destination-prob", type=float, default=0.0)
    d.add_argument("--action-noise", type=float, default=0.0)
    d.add_argument("--image-size", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    d.add_argument("--control-hz", type=int, default=20, choices=(10, 20))
    d.add_argument("--n-objects", type=int, default=3)
    d.add_argument("--policy", default=None, help="record this bussing zoo policy instead of the scripted expert")
    d.add_argument("--allow-swap-all", action="store_true",
                   help="let --wrong-destination-prob send every object of an episode to the other container (a "
                        "reverse-bussing episode; off by default so that world-model data never holds one)")
    ds = sub.add_parser("demos-stats", help="what demo stores hold: tasks, sources, objects in the other container")
    ds.add_argument("--store", nargs="+", required=True)
    e = sub.add_parser("eval", help="evaluate a zoo policy in the simulator")
    e.add_argument("--policy", required=True)
    e.add_argument("--task", default="bussing", choices=("bussing", "reverse"))
    e.add_argument("--episodes", type=int, default=36)
    e.add_argument("--out", default=None)
    e.add_argument("--no-videos", action="store_true")
    e.add_argument("--image-size", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    z = sub.add_parser("zoo-train", help="regenerate the zoo's demos and weights")
    z.add_argument("--workdir", default="/tmp/sc3_zoo")
    z.add_argument("--out", default=None)
    ze = sub.add_parser("zoo-eval", help="evaluate every zoo policy on its task and write the table")
    ze.add_argument("--out", required=True)
    ze.add_argument("--episodes", type=int, default=36)
    ze.add_argument("--no-videos", action="store_true")
    ze.add_argument("--policies", nargs="*", default=None, help="zoo policies to evaluate (default: all)")
    sub.add_parser("zoo-list", help="list zoo policies")
    a = ap.parse_args(argv)
    if a.cmd == "demos":
        res = demos(a.out, a.episodes, a.seed, a.grasp_noise, a.release_noise, a.wrong_destination_prob,
                    a.action_noise, tuple(a.image_size), a.control_hz, a.n_objects, policy=a.policy,
                    allow_swap_all=a.allow_swap_all)
    elif a.cmd == "demos-stats":
        from .demos import store_contents
        res = store_contents(*a.store)
    elif a.cmd == "eval":
        res = eval(a.policy, a.task, a.episodes, a.out, not a.no_videos, tuple(a.image_size))
    elif a.cmd == "zoo-train":
        from .zoo import ZOO_DIR
        from .zoo_train import train_zoo
        res = train_zoo(a.workdir, a.out or ZOO_DIR)
    elif a.cmd == "zoo-eval":
        from .policy_eval import evaluate_zoo
        print(evaluate_zoo(a.out, a.episodes, not a.no_videos, a.policies))
        return 0
    else:
        from .zoo import ZOO
        res = {n: {"task": e.task, "recipe": e.recipe} for n, e in ZOO.items()}
    print(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
