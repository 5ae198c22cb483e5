"""MuJoCo table-bussing benchmark: scene, tasks (bussing / reverse), ground-truth criteria, scripted expert,
demonstration generator, a zoo of learned pixel policies, and policy evaluation. Needs the ``[sim]`` extra.

Importing this package picks a headless GL backend *before* MuJoCo is imported: ``MUJOCO_GL`` defaults to ``egl``,
and ``osmesa`` is replaced by ``egl`` when the OSMesa library is not installed (as on the Debian images used here).
"""
from __future__ import annotations

import ctypes.util
import os
import warnings


def _pick_gl_backend() -> None:
    want = os.environ.get("MUJOCO_GL", "")
    if want == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        warnings.warn("MUJOCO_GL=osmesa but libOSMesa is not installed; using egl", RuntimeWarning, stacklevel=2)
        want = ""
    if not want:
        want = "egl"
    os.environ["MUJOCO_GL"] = want
    if want in ("egl", "osmesa"):
        os.environ["PYOPENGL_PLATFORM"] = want


_pick_gl_backend()
