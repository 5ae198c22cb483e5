"""``sc3 train-detector --data STORE --out DIR``: a success detector learnt from a lab's own labelled episodes
(``sc3_jax/evaluation/success_detector.py``), to score imagined rollouts: ``sc3 sweep episodes --scorer detector:DIR``."""
from __future__ import annotations

import dataclasses

from sc3_jax.commands import parse
from sc3_jax.evaluation.success_detector import DetectorConfig

SUMMARY = "a success detector from labelled episodes, to score imagined rollouts"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True, kw_only=True)
class Args(DetectorConfig):
    """Train a success detector on an episode store whose episodes carry a boolean label (`sc3 data import-lerobot`
    keeps LeRobot's next.success as labels.success); the last tenth of the episodes measure it."""

    data: str
    """an episode store of the robot, with labels (e.g. `sc3 data import-lerobot --data DATASET --out STORE`)"""
    out: str
    """where detector.npz and detector.json go"""
    progress: bool = True
    """progress bars on stderr (--no-progress: none, for batch logs)"""


def main(argv: list[str]) -> int:
    from sc3_jax.evaluation import success_detector

    a = parse(Args, argv, "train-detector")
    cfg = DetectorConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(DetectorConfig)})
    info = success_detector.train(a.data, a.out, cfg, a.progress)
    t, h = info["train"], info["heldout"]
    print(f"detector: {a.out} ({t['frames']} frames of {t['episodes']} episodes, {t['done_frames']} done)")
    if h:
        rate = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        print(f"held out ({h['episodes']} episodes): frame accuracy {h['frame_accuracy']:.2f}; the episode rule "
              f"agrees with the labels on {h['episode_agreement']:.2f} (done found {rate(h['done_found'])}, "
              f"false done {rate(h['false_done'])})")
    else:
        print("no held-out episodes (fewer than 10 labelled): nothing measured")
    print(f"use it: sc3 sweep episodes ... --scorer detector:{a.out}")
    return 0
