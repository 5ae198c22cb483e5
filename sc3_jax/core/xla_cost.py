"""FLOPs of a lowered XLA program, as the planner and the benchmarks count them."""
from __future__ import annotations


def flops(lowered, compiled: bool) -> float:
    def count(c):
        c = c[0] if isinstance(c, (list, tuple)) and c else c
        return None if not c or "flops" not in c else float(c["flops"])
    # the lowered module's count needs no compile, but some backends give none (CUDA under jax 0.11: None, seen on
    # an H200 on 2026-11-26); the compiled module's count stands in there
    flops = None if compiled else count(lowered.cost_analysis())
    if flops is None:
        flops = count(lowered.compile().cost_analysis())
    if flops is None:
        raise RuntimeError("XLA's cost analysis gave no FLOP count on this backend (lowered or compiled)")
    return flops
