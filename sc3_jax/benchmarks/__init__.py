"""Benchmarks: each a plug-in of the evaluation core (sc3_jax/evaluate), which never imports one. A benchmark
supplies initial conditions from its seeds, real rollouts from its simulator, a scorer and its policies."""
