"""``sc3 diagnose --world-model WM --data HELDOUT_STORE [--SECTION.FIELD VALUE ...]``: the checks that gate a
world-model checkpoint, on held-out episodes (sc3_jax/evaluation/diagnose.py, docs/world_model.md#diagnostics)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from sc3_jax.commands import parse_evaluated
from sc3_jax.evaluation import benchmark
from sc3_jax.evaluation.diagnose import DiagnoseConfig, Stage
from sc3_jax.evaluation.world_model_defaults import SamplerSteps

SUMMARY = "the checks that gate a world-model checkpoint, on held-out episodes"  # the line `sc3 --help` shows

D = DiagnoseConfig()  # the library's defaults, one home


@dataclasses.dataclass(frozen=True)
class Args(SamplerSteps):
    """Diagnostics that gate a world-model checkpoint on held-out episodes: PSNR against copy-last / temporal-median
    baselines, drift, true vs shuffled and counterfactual actions, inverse dynamics, offline outcome reproduction,
    then the gates' verdicts. Sampled as `sc3 sweep` samples (sc3_jax/evaluation/world_model_defaults.py;
    --sample-steps None: the model's own); every field of the world model's config is an option: --SECTION.FIELD
    VALUE, e.g. --rollout.episode-seconds 6 (the list: `sc3 train --help`)."""

    world_model: str
    """a `sc3 train` workdir or an exported world model"""
    data: str
    """held-out episode store"""
    against: str | None = None
    """a second world model of the same robot (cameras, image size, frame rate, control rate, actions): both are
    diagnosed on the same episodes, the dense probe on the same windows with the same noise (its stage is added), and
    the table is the paired comparison, A (--world-model) - B (this) with 95% intervals over episodes; --out: both
    results and the comparison"""
    episodes: int | None = D.episodes
    """N episodes evenly spaced over the store (None: all)"""
    cf_starts: int = D.cf_starts
    """counterfactual starts per episode"""
    cf_fraction: float = D.cf_fraction
    """counterfactual shift of each action axis, a fraction of that axis's recorded std (the model's norm stats)"""
    carry_px: float = D.carry_px
    """pixels a real object must move with the arm to count as carried"""
    out: str | None = None
    """also write the result as JSON here (WM/diagnose.json, in --world-model WM, is where `sc3 report` and `sc3
    diagnose-table` look)"""
    filmstrips: str | None = None
    """a folder for one filmstrip per stage of the objects-kept table (real above imagined, the first episode; None:
    beside --out, in OUT_filmstrips/, or none without --out)"""
    seed: int = D.seed
    """sampler noise and the action shuffle"""
    max_seconds: float | None = D.max_seconds
    """cap on the open-loop horizon in seconds (None: the longest episode)"""
    batch: int = D.batch
    """rollouts per jitted call (rounded up to the device count)"""
    moving_threshold: float = D.moving_threshold
    """a pixel moves when any channel differs from the last real context frame by more than this, in [-1, 1] units"""
    horizons: tuple[float, ...] = D.horizons
    """drift curve points in seconds"""
    perception: str | None = D.perception
    """weights for the benchmark's outcome scorer, the outcome check's (None: the benchmark's own)"""
    progress: bool = D.progress
    """a progress bar on stderr (--no-progress: none, for batch logs)"""
    benchmark: str = "none"
    """whose measures the passes read besides the generic ones: a benchmark's name (sc3_jax/evaluation/benchmark.py:
    bussing, the simulated benchmark's perception outcome scorer, its objects' pixels and positions; so101, the
    block's and the goal marker's pixels, the arm's and the block's image positions, what its actions move in its
    state, no outcome scorer) or package.module:attr; none: the generic measures alone (the arm read by the median
    rule, no outcome scorer, no objects kept), since a model of any robot can be diagnosed"""
    stages: tuple[Stage, ...] = D.stages
    """the passes to run: teacher_forced (one chunk ahead, shuffled actions, inverse dynamics), counterfactual,
    open_loop (drift and outcome reproduction), dense (not by default: the object 0.5 s and 1 s after real context on
    every window in which the real arm carries it, a --benchmark with object locators); the others' sections and gates
    read "not run". --stages open_loop: a large outcome set at the cost of its open-loop rollouts alone"""


def main(argv: list[str]) -> int:
    a, cfg = parse_evaluated(Args, argv, "diagnose")
    strips = a.filmstrips or (str(Path(a.out).with_suffix("")) + "_filmstrips" if a.out else None)
    check(a, strips)  # at the door: a bad bound or an unwritable path is one line before any rollout
    if a.filmstrips and not benchmark.get_or_none(a.benchmark).measures:  # asked for, it wrote none without a word
        from sc3_jax.core.errors import UserError

        raise UserError(f"--filmstrips {a.filmstrips}: --benchmark {a.benchmark} has no scene measure, so there are "
                        "no objects-kept filmstrips to write; give a --benchmark with one (bussing, so101), or leave "
                        "--filmstrips out")
    from sc3_jax.evaluation import diagnose

    fields = {f.name for f in dataclasses.fields(DiagnoseConfig)}
    dc = DiagnoseConfig(**{k: v for k, v in dataclasses.asdict(a).items() if k in fields})
    if a.against:
        return _against(a, argv, cfg, dc, strips)
    scorer_for, scene = benchmark_hooks(a.benchmark)
    result = diagnose.diagnose(a.world_model, a.data, dc, model_config=cfg, scorer_for=scorer_for, scene=scene,
                               filmstrips=strips, locators=benchmark_locators(a.benchmark),
                               category_names=benchmark.get_or_none(a.benchmark).category_names)
    print(diagnose.render_table(result))
    st = result["settings"]
    print(f"sampler: {st['sample_steps']} forward Euler steps, U re-read in {st['inverse_steps']} (`sc3 sweep`'s "
          "unless --sample-steps / --inverse-steps say otherwise); what each gate means: "
          "docs/world_model.md#diagnostics")
    print("\n".join(diagnose.verdict(result)))
    if a.out:
        print(f"result: {diagnose.save_result(result, a.out)}")
    return 0


def _against(a: Args, argv: list[str], cfg, dc: DiagnoseConfig, strips: str | None) -> int:
    """``--against B``: A and B diagnosed alike (B's config under the same sampler settings and overrides), the dense
    probe among the stages, then the paired table (``diagnose_paired``)."""
    from sc3_jax.commands import parse_with_config
    from sc3_jax.evaluation import diagnose, diagnose_paired
    from sc3_jax.evaluation.world_model_defaults import Sampler, evaluation_config, warn_if_student_off_its_step
    from sc3_jax.model import checkpoint

    _, cfg_b = parse_with_config(Args, argv, "diagnose", lambda x: evaluation_config(
        checkpoint.read_config(x.against, "--against "), Sampler(sample_steps=x.sample_steps,
                                                                  inverse_steps=x.inverse_steps)))
    warn_if_student_off_its_step(cfg_b)
    diagnose_paired.check_same_robot(a.world_model, cfg, a.against, cfg_b)
    dc = dataclasses.replace(dc, stages=tuple(dict.fromkeys(dc.stages + ("dense",))))
    scorer_for, scene = benchmark_hooks(a.benchmark)
    locators, names = benchmark_locators(a.benchmark), benchmark.get_or_none(a.benchmark).category_names
    results = [diagnose.diagnose(wm, a.data, dc, model_config=c, scorer_for=scorer_for, scene=scene,
                                 filmstrips=strips and str(Path(strips) / side), locators=locators,
                                 category_names=names)
               for wm, c, side in ((a.world_model, cfg, "a"), (a.against, cfg_b, "b"))]
    cmp = diagnose_paired.compare(*results, seed=dc.seed)
    print("\n".join(diagnose_paired.lines(cmp)))
    if a.out:
        print(f"result: {diagnose.save_result({'paired': cmp, 'a': results[0], 'b': results[1]}, a.out)}")
    return 0


def check(a: Args, strips: str | None) -> None:
    """One-line UserErrors for the options that would fail later (a traceback, or a write after the whole
    diagnosis): counts below 1, non-finite or non-positive amounts, an output under a file or onto a folder."""
    from sc3_jax.core.errors import UserError

    def positive(flag, x, what, most=None):
        if not (isinstance(x, (int, float)) and math.isfinite(x) and x > 0):
            raise UserError(f"{flag} {x}: {what}")
        if most is not None and x > most[0]:  # a count past any store, or an amount no episode is
            raise UserError(f"{flag} {x}: at most {most[0]} ({most[1]})")
    if a.episodes is not None:
        positive("--episodes", a.episodes, "at least 1 held-out episode (leave it out: all of the store's)",
                 (1_000_000, "held-out episodes"))
    positive("--batch", a.batch, "at least 1 rollout per jitted call", (4096, "rollouts per jitted call"))
    positive("--cf-starts", a.cf_starts, "at least 1 counterfactual start per episode (--stages without "
                                         "counterfactual skips the pass)", (10_000, "starts per episode"))
    positive("--cf-fraction", a.cf_fraction, "a positive fraction of each action axis's std",
             (100, "action stds"))
    positive("--carry-px", a.carry_px, "a positive number of pixels", (100_000, "pixels"))
    if a.max_seconds is not None:
        positive("--max-seconds", a.max_seconds, "a positive number of seconds (leave it out: the longest episode)",
                 (86_400, "seconds, a day"))
    for h in a.horizons:
        positive("--horizons", h, "positive numbers of seconds", (86_400, "seconds, a day"))
    if a.out:
        _under_a_folder("--out", Path(a.out))
        if Path(a.out).is_dir():
            raise UserError(f"--out {a.out}: is a folder; give the JSON file's path, e.g. {Path(a.out) / 'diagnose.json'}")
    if strips:
        flag = "--filmstrips" if a.filmstrips else "--out (its filmstrips folder)"
        _under_a_folder(flag, Path(strips))
        if Path(strips).exists() and not Path(strips).is_dir():
            raise UserError(f"{flag} {strips}: is a file, not a folder for the filmstrips")
        from sc3_jax.core.validate import out_dir
        out_dir(strips, flag)  # a link there: nothing is written through it


def _under_a_folder(flag: str, path: Path) -> None:
    """The nearest existing ancestor of ``path`` must be a folder (else nothing can be written there)."""
    from sc3_jax.core.errors import UserError
    for up in path.absolute().parents:
        if up.exists():
            if not up.is_dir():
                raise UserError(f"{flag} {path}: {up} is a file, not a folder")
            return


def benchmark_hooks(name: str):
    """(outcome scorer factory or None, scene measures by name) of the benchmark ``name`` (``--benchmark``: a
    registered name or package.module:attr, ``sc3_jax.evaluation.benchmark.get``; "none": neither)."""
    bm = benchmark.get_or_none(name)
    return bm.outcome_scorer, dict(bm.measures)


def benchmark_locators(name: str):
    """The benchmark's ``Locators`` (where its arm and objects are, what its actions move), or None ("none", or a
    benchmark without them: the arm is then read by the median rule)."""
    return benchmark.get_or_none(name).locators
