"""Video decoding for the LeRobot reader, with PyAV: the frames of an mp4 shown at given times (``decode_video``),
seeking to the keyframe before the window and decoding forward."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sc3_jax.data.lerobot_error import LeRobotError


def decode_video(path: Path, times: np.ndarray, tolerance_s: float) -> np.ndarray:
    """Decode the frames of ``path`` shown at ``times`` (seconds, ascending): uint8 [len(times), H, W, 3].

    Seeks to the keyframe before the first time, then decodes forward, so a window costs about its own length
    plus one GOP. A requested time with no frame within ``tolerance_s`` means the video and the parquet disagree.
    """
    try:
        import av
    except ImportError as e:
        raise LeRobotError(path, "decoding videos needs PyAV: pip install 'sc3_jax[lerobot]'") from e
    if not path.exists():
        raise LeRobotError(path, "missing video file")
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as e:
        raise LeRobotError(path, f"cannot open video: {e}") from e
    with container:
        if not container.streams.video:
            raise LeRobotError(path, "no video stream")
        stream = container.streams.video[0]
        if stream.codec_context is None:  # FFmpeg knows no decoder for this stream's codec
            raise LeRobotError(path, f"codec {_codec_tag(stream)!r} cannot be decoded by this PyAV/FFmpeg build")
        codec = stream.codec_context.name
        target = max(0, int((times[0] - tolerance_s) / stream.time_base))
        try:
            out, last = _scan(container, stream, times, tolerance_s, target)
            if out is None and target > 0:  # the seek landed past the window (odd index): decode from the start
                out, last = _scan(container, stream, times, tolerance_s, 0)
        except av.error.FFmpegError as e:
            raise LeRobotError(path, f"codec {codec!r}: decoding failed ({e}): a corrupt file, or a codec this "
                                     f"PyAV/FFmpeg build cannot decode") from e
    where = "none" if last is None else f"{last:.4f} s"
    if out is None:
        raise LeRobotError(path, f"no frame at t={times[0]:.4f} s (first frame at {where}): inconsistent "
                                 f"timestamps between video and parquet")
    if len(out) < len(times):
        raise LeRobotError(path, f"inconsistent lengths: video ends (last frame at {where}) before "
                                 f"t={times[len(out)]:.4f} s; it has fewer frames than the episode")
    return np.stack(out)


def _scan(container, stream, times: np.ndarray, tol: float, seek_to: int):
    """Frames at ``times`` decoding forward from ``seek_to`` -> (frames, last time seen); frames is None when the
    first frame decoded is already past ``times[0]``, a missing frame in the middle raises."""
    container.seek(seek_to, stream=stream, backward=True)
    out, last = [], None
    for frame in container.decode(stream):
        last = frame.time
        if last is None:
            raise LeRobotError(container.name, "video frames carry no timestamps")
        if last < times[len(out)] - tol:
            continue  # before the window (decoding starts at the keyframe before it)
        if last > times[len(out)] + tol:
            if not out:
                return None, last
            raise LeRobotError(container.name, f"no frame at t={times[len(out)]:.4f} s (next frame at {last:.4f} s):"
                                               f" inconsistent timestamps between video and parquet")
        out.append(frame.to_ndarray(format="rgb24"))
        if len(out) == len(times):
            break
    return out, last


def _codec_tag(stream) -> str:
    try:
        return stream.codec_tag or "unknown"
    except Exception:  # noqa: BLE001 - only used to word an error message
        return "unknown"
