"""Where one online chunk's time goes on this machine (the shipped world model, a zoo policy, batch B):

    nice python bench/profile_chunk.py [--batch 6] [--repeats 3]

Each piece is jitted alone and timed after compilation (median of ``--repeats``): the policy, the observation with
the gripper-state reader, the tokenizer's encode of the context and decode of the kept frames, one DiT pass over
every token, the whole model step (``rollout.ChunkFns.model_step``) at today's 8 + 2 and the new default's 2 + 1
(forward + inverse) Euler steps, and the perception scorer reading one finished rollout's every cut. A forward and an
inverse Euler step each cost one DiT pass (every token, full context attention); the per-step cost inside the model
step is the slope between its two measured step counts. Prints a
markdown table (docs/sweep.md#where-an-online-chunks-time-goes) and, last, ``profile_chunk: step_s=<x>
fixed_s=<y> chunk_8_2_s=<z> chunk_2_1_s=<w>`` per chunk at batch B (fixed: the model step outside its Euler steps)."""
from __future__ import annotations

import argparse
import math
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np


def timed(fn, repeats: int) -> float:
    jax.block_until_ready(fn())  # compile
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--policy", default="bus_bc_full")
    a = ap.parse_args(argv)

    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout
    from sc3_jax.core.config import replace
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    from sc3_jax.benchmarks.bussing.source import initial_observation
    from sc3_jax.benchmarks.bussing.sweep import SHIPPED_WORLD_MODEL, STATE_READER_FILE
    from sc3_jax.benchmarks.bussing.policy_eval import make_env
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition, task_id
    from sc3_jax.benchmarks.bussing.zoo import load_policy

    cfg, stats, params = checkpoint.load(str(SHIPPED_WORLD_MODEL))
    robot = checkpoint.read_robot(SHIPPED_WORLD_MODEL, cfg)  # its data's frame rate, as every command reads it
    cfg = replace(cfg, rollout=dict(episode_seconds=12.0))
    reader = perception.state_reader(perception.load(str(SHIPPED_WORLD_MODEL / STATE_READER_FILE)))
    policy = load_policy(a.policy)
    B = a.batch
    env = make_env(tuple(cfg.data.image_size))
    seeds = [10_000_000 + i for i in range(B)]
    obs0 = [initial_observation(env, s, "bussing") for s in seeds]

    def rollout_at(steps: int, inverse: int):
        c = replace(cfg, sample=dict(steps=steps, inverse_steps=inverse))
        return rollout.Rollout(c, stats, data_fps=robot.fps, state_reader=reader)

    ro = rollout_at(8, 2)
    s, fns = ro.spec, ro.chunk_fns
    frames0 = np.stack([np.repeat(f[:, None], s.context, 1) for f, _ in obs0])
    ics = rollout.InitialConditions(frames0, np.stack([p for _, p in obs0]), np.full(B, task_id("bussing")))
    keys = np.asarray(rollout.episode_keys(0, B))
    _, frames, state, task, kd = ro._inputs(ics, keys)
    p = ro.place_params(params)
    carry = ro._init(frames, *state)
    obs, k_pol = ro._observe(carry, task, kd, ro.reader_params)
    pol = jax.jit(jax.vmap(lambda o, k: policy.apply(policy.params, o, jax.random.wrap_key_data(k))))
    acts = pol(obs, k_pol)
    enc = jax.jit(jax.vmap(lambda c: fns.tok.encode(c)))
    latents = enc(carry.context)

    from sc3_jax.model import flow
    from sc3_jax.model import dit
    K, V, l = s.context, s.views, s.keep
    Kt, Tt = fns.window
    video = jnp.concatenate([latents, latents[:, :, :1].repeat(Tt, 2)], axis=2)  # [B, V, Kt + Tt, P, D]
    a0 = jnp.zeros((B, s.predict, 7))

    def one_pass(video, a):  # one DiT evaluation over every token: what each Euler step (FD or ID) costs
        vn = jnp.zeros((B, V, Kt + Tt), bool).at[:, :, Kt:].set(True)
        an = jnp.zeros((B, s.predict), bool)
        inp = flow.noise_inputs(video, a, jnp.full((B,), s.stride, jnp.int32), vn, an, jnp.full((B,), 0.5), video,
                                a, pose=jnp.zeros((B, s.predict + 1, 7)), context_level=jnp.zeros((B,)))
        return dit.apply(params, cfg.model, inp, fns.grid, context_frames=Kt)

    apply_s = timed(lambda: jax.jit(one_pass)(video, a0), a.repeats)
    dec = jax.jit(jax.vmap(lambda v: fns.tok.decode(v[:, K:K + l], s.image_size)))
    rows = {"policy (zoo `%s`)" % a.policy: timed(lambda: pol(obs, k_pol), a.repeats),
            "observe, with the gripper-state reader": timed(lambda: ro._observe(carry, task, kd, ro.reader_params),
                                                            a.repeats),
            "tokenizer encode (the context)": timed(lambda: enc(carry.context), a.repeats),
            "one DiT pass over every token (each forward or inverse Euler step)": apply_s,
            f"tokenizer decode (the {l} kept frames)": timed(lambda: dec(video), a.repeats)}
    step_times = {}
    for fd, idn in ((8, 2), (2, 1)):
        r = ro if (fd, idn) == (8, 2) else rollout_at(fd, idn)
        step_times[(fd, idn)] = timed(lambda: r._model_step(p, carry, acts, kd, jnp.float32(math.inf)), a.repeats)
        rows[f"model step, {fd} forward + {idn} inverse Euler steps (measured)"] = step_times[(fd, idn)]
    # the Euler step inside the model step: the slope between the two measured step counts (7 passes apart)
    slope = (step_times[(8, 2)] - step_times[(2, 1)]) / 7
    rows["one Euler step inside the model step (slope of the two rows above)"] = slope
    fixed = step_times[(2, 1)] - 3 * slope

    scorer = PerceptionScorer(perception.load(perception.DEFAULT_WEIGHTS))
    fr = np.concatenate([frames0[0][:, -1:], np.repeat(frames0[0][:, -1:], s.num_frames, 1)], 1)
    ic = make_initial_condition(seeds[0], "bussing")
    score_s = timed(lambda: scorer.score_cuts(fr, ic.objects, ic.destinations(), s.keep, s.num_chunks, prefix=1),
                    a.repeats)
    env.close()

    per_chunk = rows["observe, with the gripper-state reader"] + rows["policy (zoo `%s`)" % a.policy] + \
        step_times[(8, 2)]
    print(f"\nOne online chunk at batch {B} ({jax.devices()[0].platform}, {s.views} views, K={s.context}, "
          f"l'={s.predict}, l={s.keep}; {s.num_chunks} chunks per 12 s rollout)\n")
    print("| piece | seconds per chunk (batch) | share of an 8 + 2 step chunk |\n|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {v:.3f} | {v / per_chunk:.0%} |")
    print(f"| scoring one rollout's {s.num_chunks} cuts (perception, once per rollout) | {score_s:.3f} | "
          f"{score_s / s.num_chunks / per_chunk:.0%} (per chunk) |")
    print(f"\nprofile_chunk: step_s={slope:.3f} fixed_s={fixed:.3f} chunk_8_2_s={per_chunk:.3f} "
          f"chunk_2_1_s={per_chunk - step_times[(8, 2)] + step_times[(2, 1)]:.3f}")


if __name__ == "__main__":
    main()
