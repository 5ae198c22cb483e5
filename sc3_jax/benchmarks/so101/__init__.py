"""SO-101 pick-and-place benchmark: the third-party MuJoCo simulator ``lerobot-env-so101``
(``lerobot_env_so101/SO101PickPlace-v0``: a 5-joint SO-101 arm moves a 4 cm block onto a goal spot on the table, 10 Hz,
4-D actions dx, dy, dz in [-1, 1] and a gripper command) wrapped for our pipeline: an environment (``env.py``), a
scripted controller with failure knobs (``controllers.py``), rollouts of controllers and policies, in worker
processes too (``rollouts.py``), and a LeRobot v3.0 dataset writer (``collect.py``). Needs the ``[so101]`` extra
(``pip install -e '.[so101]'``); docs/so101.md.

Importing this package picks a headless GL backend *before* MuJoCo is imported: ``MUJOCO_GL`` defaults to ``egl``,
and ``osmesa`` is replaced by ``egl`` when the OSMesa library is not installed (``benchmarks.pick_gl_backend``, as
the bussing benchmark does).
"""
from __future__ import annotations

from sc3_jax.benchmarks import pick_gl_backend

pick_gl_backend()
