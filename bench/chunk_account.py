"""An account of one closed-loop rollout chunk (one episode) at a config's shapes, compiled on this machine and never
run (abstract inputs: nothing of the model is allocated):

    python bench/chunk_account.py [--config paper] [--depths 2 3] [--uncached]

Per part of the chunk (``flops.chunk_programs``: the tokenizer's encode of the context and decode of the kept frames,
the context's keys/values, each forward-dynamics Euler step, every frame's keys/values for the inverse read, each
inverse-dynamics step, the policy call): XLA's compiled cost analysis (FLOPs, bytes accessed) and memory analysis
(temp bytes), beside the ideal FLOPs (``flops.chunk_ideal_flops``: each Euler step runs only its noisy tokens against
cached keys/values, every clean token's keys/values are computed once, every frame is encoded and decoded once), and
the ratio. The chunk total is the whole compiled model step (S = 1) plus the other Euler steps and the policy; the
sum of the parts beside it is its check. Counted with the layers unrolled and dense attention (XLA counts a loop
body once, and a fused or blockwise kernel's tiles are loops); a deep model is compiled at two reduced depths and
extrapolated linearly per layer (printed). ``--uncached``: the same for the sampler without the context cache.

Last line: ``chunk_account <config>: ratio=<compiled/ideal> chunk_tflop=<x> ideal_tflop=<y>``."""
from __future__ import annotations

import argparse
import time

from sc3_jax.train import flops
from sc3_jax.core.config import load_config


def table(a: dict) -> str:
    rows = ["| part | runs | compiled GFLOP / run | ideal GFLOP / run | compiled / ideal | GB accessed / run "
            "| temp GB |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, p in a["parts"].items():
        ratio = f"{p['flops'] / p['ideal_flops']:.3f}" if p["ideal_flops"] else "-"
        rows.append(f"| {name} | {p['runs']} | {p['flops'] / 1e9:,.1f} | {p['ideal_flops'] / 1e9:,.1f} | {ratio} | "
                    f"{p['bytes'] / 1e9:,.2f} | {p['temp_bytes'] / 1e9:,.2f} |")
    rows.append(f"| **chunk** (model step + steps + policy) | 1 | {a['chunk_flops'] / 1e9:,.1f} | "
                f"{a['ideal_flops'] / 1e9:,.1f} | **{a['ratio']:.3f}** | {a['chunk_bytes'] / 1e9:,.2f} | "
                f"{a['model_step_temp_bytes'] / 1e9:,.2f} |")
    rows.append(f"| (sum of the parts x runs) | | {a['parts_flops'] / 1e9:,.1f} | | | | |")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="paper")
    ap.add_argument("--depths", type=int, nargs=2, default=(2, 3), help="depths compiled when the model is deeper")
    ap.add_argument("--uncached", action="store_true", help="also account the sampler without the context cache")
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    # the paper config's robot (the bussing benchmark's 7-D delta_ee actions at 20 fps) where the config does not
    # record its data's; the count depends on neither
    from sc3_jax.data.action_space import DELTA_EE
    robot = {"action_space": DELTA_EE if cfg.model.action_dim == DELTA_EE.dim else None,
             "data_fps": cfg.data.fps or 20.0}
    m, d = cfg.model, cfg.data
    out = {}
    for cache in (True, False) if args.uncached else (True,):
        t0 = time.perf_counter()
        a = out[cache] = flops.chunk_account(cfg, tuple(args.depths), cache, **robot)
        counted = (f"compiled at depth {a['counted_depths'][0]}" if len(a["counted_depths"]) == 1 else
                   f"compiled at depths {a['counted_depths'][0]} and {a['counted_depths'][1]}, extrapolated "
                   f"linearly per layer to {a['depth']}")
        print(f"\nOne chunk of `{cfg.name}` ({len(d.views)} views {d.image_size[0]}x{d.image_size[1]}, "
              f"K={d.context_frames} l'={d.future_frames} l={cfg.rollout.keep_frames}, dim {m.dim}, {m.depth} "
              f"layers, {m.dtype}, context attention {m.context_attention}, S={a['steps'][0]} forward + "
              f"{a['steps'][1]} inverse Euler steps, {'cached' if cache else 'UNCACHED'} sampler; {counted}; "
              f"{time.perf_counter() - t0:.0f} s)\n")
        print(table(a))
    print(f"\nBytes and temp memory are those of dense attention (fp32 scores written out per layer); "
          f"model.attention_impl is {m.attention_impl!r} in this config"
          + ("." if m.attention_impl == "dense" else ", whose kernel keeps the scores in tiles."))
    a = out[True]
    print(f"chunk_account {cfg.name}: ratio={a['ratio']:.3f} chunk_tflop={a['chunk_flops'] / 1e12:.1f} "
          f"ideal_tflop={a['ideal_flops'] / 1e12:.1f}"
          + (f" uncached_ratio={out[False]['ratio']:.3f}" if False in out else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
