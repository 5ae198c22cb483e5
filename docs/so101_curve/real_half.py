# The SO-101 sweep's real half for the 8 zoo policies ahead of `sc3 sweep so101` (which resumes what exists): the
# calls sweep.run() makes before the imagined rollouts. python docs/so101_curve/real_half.py OUT WORLD_MODEL
import sys
from pathlib import Path


def main():
    from sc3_jax.benchmarks.so101 import sweep
    from sc3_jax.benchmarks.so101.zoo import ZOO
    from sc3_jax.evaluation.scorers import load_outcome_scorer
    from sc3_jax.model import checkpoint
    out = Path(sys.argv[1]); wm = sys.argv[2]
    wcfg = checkpoint.read_config(wm)
    scorer = load_outcome_scorer("sc3_jax.benchmarks.so101.placed:block_placed")
    seeds = [sweep.EVAL_SEED0 + i for i in range(36)]
    views, size = tuple(wcfg.data.views), tuple(wcfg.data.image_size)
    steps = int(round(wcfg.rollout.episode_seconds * wcfg.rollout.control_hz))
    out.mkdir(parents=True, exist_ok=True)
    sweep.write_conditions(out / sweep.IC_DIR, seeds, size, views)
    sweep.real_outcomes(out, list(ZOO), seeds, steps, size, views, scorer, 2, True, wcfg.rollout.control_hz)
    print("REAL_HALF_DONE", list(ZOO))


if __name__ == "__main__":
    main()
