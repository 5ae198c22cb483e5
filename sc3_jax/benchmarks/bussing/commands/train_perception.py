"""``sc3 train-perception --data STORE ... [--out WEIGHTS]`` | ``--validate RESULTS ... --init WEIGHTS``: train the
perception scorer on simulator frames labelled by physics, or check weights against physics on a sweep's real
rollouts (``sc3_jax/benchmarks/bussing/perception_train.py``)."""
from __future__ import annotations

import dataclasses
from typing import Annotated

import tyro

from sc3_jax.commands import parse
from sc3_jax.core.errors import UserError

# the bussing benchmark's own command (its scorer, its simulator's labels), as `sc3 sim` is: --help says so
SUMMARY = "train the bussing benchmark's perception scorer, or check its weights against physics"  # `sc3 --help`


@dataclasses.dataclass(frozen=True)
class Args:
    """Train the perception scorer (per frame and object type: lifted / in the bin / in the can, and the finger
    gap) on episode stores whose labels come from the physics state, and report its held-out agreement with those
    labels per head; or, with --validate, re-score a sweep's real rollouts with the weights and report their
    agreement with physics per criterion, clean and degraded (docs/sweep.md#scorers)."""

    data: Annotated[tuple[str, ...], tyro.conf.arg(metavar="STORE [STORE ...]")] = ()
    """episode stores with meta['object_pos'] (`sc3 sim demos`); required to train"""
    generate: int = 0
    """first write this many expert episodes (both tasks) to the second-to-last --data store"""
    generate_policies: int = 0
    """and this many zoo-policy episodes (training seeds) to the last --data store"""
    policy_seed: int = 60
    """seed block of the zoo-policy episodes (simulator seeds policy_seed x 100,000 + i)"""
    init: str | None = None
    """warm-start from these weights (None: fresh weights); with --validate, the weights to check"""
    out: str | None = None
    """where the trained weights go (None: the shipped weights' file, sc3_jax/benchmarks/bussing/perception.npz, which sweeps
    read); with --validate and no --init, the weights to check"""
    steps: int = 2500
    """training steps"""
    lr: float = 1e-3
    """peak learning rate (AdamW, warmup then cosine decay)"""
    batch: int = 64
    """frames per step"""
    pos_weight: float = 1.0
    """weight of a positive predicate label in the loss (each predicate holds in only a few percent of the frames)"""
    keypoints: int | None = None
    """keypoints per view of fresh weights (None: perception.N_KP)"""
    widths: tuple[int, int, int] | None = None
    """channels of the first three conv layers of fresh weights (None: perception.WIDTHS)"""
    hidden: int | None = None
    """MLP width of fresh weights (None: perception.HIDDEN)"""
    stride: int = 2
    """train on every stride-th frame of each episode"""
    max_episodes: int | None = None
    """train on at most this many episodes (None: all of every --data store)"""
    seed: int = 0
    """initialisation, held-out split and batch seed"""
    validate: Annotated[tuple[str, ...], tyro.conf.arg(metavar="RESULTS [RESULTS ...]")] = ()
    """only print the agreement with physics of --init (or --out) on the real rollouts of these sweep results
    stores; nothing is trained"""


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "train-perception")
    if a.validate:
        return _validate(a)
    if not a.data:
        raise UserError("--data: give the episode stores to train on (or --validate RESULTS ... to check weights)")
    if a.generate and len(a.data) < 2:
        raise UserError("--generate writes to the second-to-last --data store (the last takes --generate-policies): "
                        "give at least two")
    import time

    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing import perception_train as pt

    out = a.out or str(perception.DEFAULT_WEIGHTS)
    t0 = time.time()
    if a.generate:
        pt.generate_scorer_data(a.data[-2], a.generate)
    if a.generate_policies:
        pt.generate_scorer_data(a.data[-1], a.generate_policies, seed=a.policy_seed, policies=True)
    data = pt.load_training_data(a.data, a.stride, a.max_episodes)
    init = perception.load(a.init) if a.init else None
    arch = {"n_kp": a.keypoints or perception.N_KP, "widths": tuple(a.widths or perception.WIDTHS),
            "hidden": a.hidden or perception.HIDDEN}
    params, metrics = pt.train(data, a.steps, a.batch, lr=a.lr, seed=a.seed, init=init, arch=arch,
                               pos_weight=a.pos_weight)
    metrics.update(seconds=round(time.time() - t0, 1), store=list(a.data), stride=a.stride, init=a.init, lr=a.lr,
                   batch=a.batch, pos_weight=a.pos_weight)
    perception.save(out, params, metrics)
    print("\n".join(training_summary(out, metrics, perception.PREDICATES)))
    return 0


def training_summary(out: str, m: dict, predicates) -> list[str]:
    """Where the weights went and what the held-out numbers mean (each head against the physics labels, beside the
    accuracy of always answering no)."""
    lines = [f"weights: {out} ({m['steps']} steps on {m['train_frames']:,} frames, {m['seconds']:.0f} s; the metrics "
             "below are stored in its meta)"]
    if not m.get("heldout_frames"):
        return lines + ["no held-out frames (too few episodes for a 10% hold-out): nothing measured; check the "
                        f"weights with sc3 train-perception --validate RESULTS --init {out}"]
    lines += [f"held-out episodes ({m['heldout_frames']:,} frames), each head against the physics label of the "
              "objects on the table: accuracy, precision, recall; 'always no' = the accuracy of never seeing the "
              "predicate (it holds in few frames):",
              "| head | accuracy | always no | precision | recall |", "|---|---|---|---|---|"]
    for name in predicates:
        lines.append(f"| {name} | {m[f'heldout_acc/{name}']:.3f} | {1 - m[f'heldout_positive/{name}']:.3f} | "
                     f"{m[f'heldout_precision/{name}']:.3f} | {m[f'heldout_recall/{name}']:.3f} |")
    lines += [f"| finger gap | mean abs error {m['heldout_width_mae_m'] * 1000:.1f} mm | | | |",
              f"next: how it scores rollouts, against physics: sc3 train-perception --validate RESULTS --init {out}"]
    return lines


def _validate(a: Args) -> int:
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing import perception_train as pt

    weights = a.init or a.out or str(perception.DEFAULT_WEIGHTS)
    params = perception.load(weights)
    for results in a.validate:
        got = pt.validate(results, params)
        print("\n".join(validation_summary(weights, results, got)))
    return 0


def validation_summary(weights: str, results: str, got: dict) -> list[str]:
    """One table per results store: per frames kind (clean, then each degradation generated frames show), the
    fraction of objects whose verdict on each criterion matches physics, and the majority guess's (the floor)."""
    floor = got["majority_guess"]
    keys = [k for k in floor if k != "n_objects"]
    lines = [f"{weights} against physics on the real rollouts of {results} ({floor['n_objects']:,} objects): the "
             "fraction of objects on which the scorer's verdict equals the simulator's; majority guess = every "
             "object gets each criterion's most common verdict (what the base rates alone agree)",
             "| frames | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for kind, agree in got.items():
        name = "majority guess (floor)" if kind == "majority_guess" else kind
        lines.append(f"| {name} | " + " | ".join(f"{agree[k]:.3f}" for k in keys) + " |")
    return lines
