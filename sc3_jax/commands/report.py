"""``sc3 report RESULTS ... [--out DIR]``: tables, plots and videos from a sweep's results store."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated

import tyro

from sc3_jax.core import atomic
from sc3_jax.commands import one_or_more, parse
from sc3_jax.core.errors import UserError

SUMMARY = "tables, plots and videos from a sweep's results store"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args:
    """Report of a sweep's results store."""

    results: Annotated[tyro.conf.Positional[tuple[str, ...]], one_or_more("RESULTS")]
    """the sweep's --out directory (a sharded sweep's: all its shards), or several shares of one sweep, read as one"""
    out: str | None = None
    """report directory (None: the first RESULTS/report)"""
    videos: int | None = None
    """at most this many side-by-side videos (None: one per policy)"""
    taus: tuple[float, ...] | None = None
    """termination thresholds (None: the sweep's candidates); evaluated from the stored U_chunk, no new
    rollouts. U_chunk is in the sweep's units (rollout.tau_units)"""
    draws: int = 2000
    """paired bootstrap draws for the 95% intervals"""
    real: tuple[str, ...] | None = None
    """a sweep of held-out episodes only: real outcomes of the same policies, [NAME=]PATH (episode stores with
    labels, a LeRobot dataset, a CSV; docs/your_robot.md), instead of the sweep's own --real, which the store keeps
    (real.json; without --real nothing outside the store is read for them)"""
    benchmark: str | None = None
    """whose scene measure reads the objects-kept row: a benchmark's name or package.module:attr (None: the one the
    store's sweep recorded; a store that records none gets no such row)"""


MAX_DRAWS = 100_000  # a paired bootstrap's intervals settle long before; 2e8 draws took 3 GB


def check_options(a: Args) -> None:
    """Each numeric option within what the report can use, in one line (``--draws 0`` was a traceback)."""
    from sc3_jax.core import validate

    validate.in_range("--draws", a.draws, 10, MAX_DRAWS, "paired bootstrap draws")
    if a.videos is not None:
        validate.in_range("--videos", a.videos, 0, 1000, "side-by-side videos")
    validate.taus(a.taus)


def scene_of(results: str, name: str | None = None):
    """The scene measure a store's objects-kept row is read with: that of the benchmark ``name`` (``--benchmark``),
    else of the one the store's sweep recorded (``benchmark.json``, as ``sc3 sweep NAME`` was given it: a built-in
    name; a package.module:attr there is refused, as the store is data and may come from anyone, until
    ``--benchmark`` names it; from before it, ``real_frames/scene.json``, one of the built-in names). None when no
    benchmark is named (a store of ``sc3 sweep episodes``, of any robot: no objects-kept row) or the benchmark has no
    scene measure."""
    from sc3_jax.evaluation import benchmark
    from sc3_jax.evaluation.report_episodes import REAL_FRAMES
    from sc3_jax.core.validate import json_object

    if name is None:
        name = benchmark.recorded(results)
        if name is not None and name not in benchmark.names():  # a store is data: it names no code to import
            raise UserError(f"{Path(results) / benchmark.STORE_FILE}: the store was swept by {name!r}, code outside "
                            f"sc3_jax; sc3 report imports only what its command line names: add --benchmark {name}")
    if name is None:
        saved = Path(results) / REAL_FRAMES / "scene.json"
        if not saved.is_file():
            return None  # no benchmark named: the generic report, no benchmark's objects guessed at
        name = json_object(atomic.read_json(saved), str(saved), "delete it and rerun the sweep").get("benchmark")
        if name not in benchmark.names():  # the file is data: only a built-in benchmark's measure runs
            raise UserError(f"{saved}: unknown benchmark {name!r} (known: {', '.join(benchmark.names())})")
    try:
        return benchmark.get(name).scene
    except UserError as e:
        raise UserError(f"{results}: {e} (--benchmark NAME reads the store with another's measure)") from None


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "report")
    if not a.results:  # tyro takes a positional tuple as zero or more; argparse asked for one at least
        raise UserError("give at least one RESULTS store")
    check_options(a)
    from sc3_jax.evaluation import report  # after parsing: --help and a typo need not load plotting

    md = report.render(list(a.results), a.out, a.videos, a.taus, a.draws, scene=scene_of(a.results[0], a.benchmark),
                       real=a.real)
    t = json.loads((md.parent / "report.json").read_text())
    from sc3_jax.evaluation import eval_info  # LeRobot's format beside ours, so a lab's dashboards read the sweep

    infos = [f for r in a.results for f in eval_info.write(r, md.parent / "eval_info" / (Path(r).name if
                                                                                         len(a.results) > 1 else ""))]
    print("\n".join(report.closing_lines(t)))
    print(f"report: {md} (and report.html, report.json; {len(infos)} eval_info.json in lerobot-eval's shape under "
          f"{md.parent / 'eval_info'})")
    return 0
