"""Benchmarks: each a plug-in of the evaluation core (sc3_jax/evaluation), which never imports one. A benchmark
supplies initial conditions from its seeds, real rollouts from its simulator, a scorer and its policies.

Both simulators render headless with MuJoCo; ``pick_gl_backend`` is the choice every benchmark package makes on
import, before MuJoCo is imported."""
from __future__ import annotations

import ctypes.util
import os
import warnings


def pick_gl_backend() -> None:
    """``MUJOCO_GL`` defaults to ``egl``; ``osmesa`` is replaced by ``egl`` when the OSMesa library is not installed
    (as on the Debian images used here)."""
    want = os.environ.get("MUJOCO_GL", "")
    if want == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        warnings.warn("MUJOCO_GL=osmesa but libOSMesa is not installed; using egl", RuntimeWarning, stacklevel=2)
        want = ""
    if not want:
        want = "egl"
    os.environ["MUJOCO_GL"] = want
    if want in ("egl", "osmesa"):
        os.environ["PYOPENGL_PLATFORM"] = want
