"""Writing frames to an mp4 file: the one place that does (rollouts, the sweep's report, annotation, the simulator's
evaluation videos). OpenCV only; importing this does not import the simulator (whose package sets up GL)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sc3_jax.core import atomic


def write_mp4(path: str | Path, frames: np.ndarray, fps: float) -> None:
    """``frames`` uint8 RGB [T, H, W, 3] -> ``path`` (mp4v codec) played at ``fps`` (the frames' rate, the caller's),
    written whole or not at all (``atomic``: a kill mid-video leaves the previous file, not a truncated one)."""
    import cv2
    frames = np.asarray(frames)
    h, w = frames.shape[1:3]
    with atomic.replacing(path) as tmp:  # the temporary keeps the .mp4 suffix OpenCV picks the container by
        vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not vw.isOpened():
            raise RuntimeError(f"OpenCV could not open an mp4v writer for {path}")
        for f in frames:
            vw.write(np.ascontiguousarray(f[..., ::-1]))  # RGB -> OpenCV's BGR
        vw.release()
