"""MuJoCo table-bussing benchmark: scene, tasks (bussing / reverse), ground-truth criteria, scripted expert,
demonstration generator, a zoo of learned pixel policies, and policy evaluation. Needs the ``[sim]`` extra.

Importing this package picks a headless GL backend *before* MuJoCo is imported: ``MUJOCO_GL`` defaults to ``egl``,
and ``osmesa`` is replaced by ``egl`` when the OSMesa library is not installed (as on the Debian images used here).
"""
from __future__ import annotations

from sc3_jax.benchmarks import pick_gl_backend

pick_gl_backend()
