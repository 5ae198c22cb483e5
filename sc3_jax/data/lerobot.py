"""Read LeRobot datasets (codebase v2.0/v2.1 and v3.0) with pyarrow and PyAV only.

The ``lerobot`` package pins old torch/opencv/numpy, so we read its on-disk format directly:

* ``meta/info.json``: codebase_version, fps, features, path templates.
* v3.0: ``meta/episodes/chunk-*/file-*.parquet`` (one row per episode: where its rows and video segments live),
  ``meta/tasks.parquet``; many episodes share one data parquet and one mp4 per camera, an episode's frame ``t``
  sits at ``from_timestamp + timestamp[t]`` inside its mp4.
* v2.x: ``meta/episodes.jsonl``, ``meta/tasks.jsonl``; one parquet and one mp4 per camera per episode (t = 0 at the
  episode's first frame).
* Cameras are ``"dtype": "video"`` features (decoded with PyAV: h264, AV1 via libdav1d, ...) or ``"dtype": "image"``
  features stored in the data parquet as ``struct<bytes, path>`` (PNG bytes).

Frames are decoded lazily: :meth:`LeRobotEpisodes.window` decodes just the requested span (seeking to the nearest
keyframe), :meth:`LeRobotEpisodes.episode` returns the tabular data at once and decodes ``frames`` on first access.
Every problem with the input raises :class:`LeRobotError` naming the file or key at fault.

:func:`import_lerobot` converts a dataset into our episode store (``sc3_jax.data.episodes``), with the action space
the dataset is declared to have (LeRobot's info.json has no such declaration: the caller gives it, or our own
export's ``sc3_action_space`` entry does).
"""
from __future__ import annotations

import functools
import json
import math
import os
import re
from collections import OrderedDict
from pathlib import Path

import numpy as np

from sc3_jax.core import locks
from sc3_jax.core.errors import UserError
from sc3_jax.core.safe_names import ALLOWED, is_safe, join_inside
from sc3_jax.core.validate import is_count, is_finite_number, json_object, regular_file

try:
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError as e:  # pragma: no cover - depends on the install
    raise ImportError("reading LeRobot datasets needs pyarrow: pip install 'sc3_jax[lerobot]'") from e

SUPPORTED_VERSIONS = ("v2.0", "v2.1", "v3.0")
IMAGE_PREFIX = "observation.images."
# info.json key of our action-space declaration (LeRobot has none): our export writes it, import reads it back
INFO_ACTION_SPACE = "sc3_action_space"
SUCCESS_KEY = "next.success"  # LeRobot's per-frame success feature (evaluation/labels.py: LEROBOT_SUCCESS)
MIN_EPISODE_FRAMES = 2  # an imported episode shorter than this is skipped (said): nothing can be learnt from it
LABELS_FIELD = "labels"  # an imported episode's meta.json {criterion: bool}, what `sc3 sweep episodes --real STORE` reads
_OPTIONAL = object()  # sentinel: "use observation.state if the dataset has it"


class LeRobotError(UserError):
    """A LeRobot dataset we cannot read as asked (a UserError: one line in every command that reads one).
    ``where`` names the file or feature key at fault."""

    def __init__(self, where: str | os.PathLike, problem: str):
        self.where, self.problem = str(where), problem
        super().__init__(f"{where}: {problem}")


def read_info(path: Path) -> dict:
    """A LeRobot dataset's ``meta/info.json``, checked where it enters: its rate, features and path templates have
    the types the reader needs (a retyped one is one line naming it, not a TypeError where it is first used)."""
    from sc3_jax.core import atomic

    fix = "restore it from the dataset's source"
    info = json_object(atomic.read_json(path, fix), str(path), fix)

    def need(key: str, ok: bool, want: str):
        if not ok:
            raise LeRobotError(path, f"{key} is {info.get(key, 'missing')!r}, expected {want}; {fix}")
    need("fps", is_finite_number(info.get("fps")) and 0 < info["fps"] <= 10_000, "a positive frame rate")
    need("features", isinstance(info.get("features"), dict) and all(
        isinstance(f, dict) and isinstance(f.get("shape", []), list) for f in info["features"].values()),
         "{key: {dtype, shape, ...}}")
    for key in ("data_path", "video_path"):
        need(key, isinstance(info.get(key, ""), str) or info.get(key) is None, "a path template")
    need("chunks_size", info.get("chunks_size") is None or is_count(info["chunks_size"]), "a positive integer")
    return info


def view_name(key: str) -> str:
    """Our view name for a camera key: ``observation.images.wrist`` -> ``wrist``."""
    return key[len(IMAGE_PREFIX):] if key.startswith(IMAGE_PREFIX) else key.rsplit(".", 1)[-1]


class LeRobotEpisode:
    """One episode, resampled to the reader's fps. Tabular fields are arrays; ``frames`` decodes on first access."""

    def __init__(self, source: LeRobotEpisodes, index: int, episode_index: int, timestamps: np.ndarray,
                 actions: np.ndarray, state: np.ndarray | None, prompt: str, tasks: list[str],
                 pose: np.ndarray | None = None, success: bool | None = None):
        self._source, self.index, self.episode_index = source, index, episode_index
        self.timestamps, self.actions, self.state, self.pose = timestamps, actions, state, pose
        self.prompt, self.tasks = prompt, tasks
        self.success = success  # any frame's next.success (None: the dataset has no such feature)
        self.fps = source.fps

    @property
    def length(self) -> int:
        return len(self.timestamps)

    def __len__(self) -> int:
        return self.length

    @functools.cached_property
    def frames(self) -> dict[str, np.ndarray]:
        """view -> uint8 [T, H, W, 3] for the whole episode."""
        return self._source.window(self.index, 0, self.length)


class LeRobotEpisodes:
    """Random access to the episodes of a LeRobot dataset at ``root``.

    views: ``None`` = every camera (``observation.images.X`` becomes view ``X``); a list of view names or feature
        keys; or a dict ``{view: feature key}`` to rename cameras. Order is kept: it becomes our view order.
    wrist_views: which views are wrist cameras (default: names containing "wrist"); the rest are third-person.
    fps: resample to this rate. Only integer-ratio subsampling is supported (every k-th frame, actions included:
        LeRobot actions are usually absolute targets; delta actions should be imported at the native rate and
        composed by the training pipeline's strides instead).
    action_key / state_key: column names. ``state_key=None`` ignores the state; by default ``observation.state``
        is used when present. ``pose_key``: a column read as ``pose`` too (None: none).
    cache_size: how many decoded (episode, view, span) windows to keep, least recently used out first; 0 = none.
    tolerance_s: how far a decoded video frame may sit from the requested time (default a quarter frame period).
    """

    def __init__(self, root: str | os.PathLike, views: list[str] | dict[str, str] | None = None,
                 wrist_views: list[str] | None = None, fps: float | None = None, action_key: str = "action",
                 state_key: str | None = _OPTIONAL, cache_size: int = 0,  # type: ignore[assignment]
                 tolerance_s: float | None = None, pose_key: str | None = None):
        self.root = Path(root)
        info_path = self.root / "meta" / "info.json"
        if not info_path.exists():
            raise LeRobotError(info_path, "missing (not a LeRobot dataset root)")
        self.info = read_info(info_path)
        self.version = str(self.info.get("codebase_version"))
        if self.version not in SUPPORTED_VERSIONS:
            raise LeRobotError(info_path, f"unsupported codebase_version {self.version!r} "
                                          f"(supported: {', '.join(SUPPORTED_VERSIONS)})")
        for key in ("fps", "features"):
            if key not in self.info:
                raise LeRobotError(info_path, f"no {key!r} entry")
        self.features: dict = self.info["features"]
        self.source_fps = float(self.info["fps"])
        self.stride = _stride(self.source_fps, fps, info_path)
        self.fps = self.source_fps / self.stride
        self.cameras = _camera_map(self.features, views, info_path)
        wrist = [v for v in self.cameras if "wrist" in v] if wrist_views is None else list(wrist_views)
        for v in wrist:
            if v not in self.cameras:
                raise LeRobotError(info_path, f"wrist view {v!r} is not one of the views {list(self.cameras)}")
        self.wrist_views = tuple(wrist)
        self.third_person_views = tuple(v for v in self.cameras if v not in wrist)
        if action_key not in self.features:
            raise LeRobotError(info_path, f"action key {action_key!r} not in features {sorted(self.features)}")
        self.action_key = action_key
        if state_key is _OPTIONAL:
            state_key = "observation.state" if "observation.state" in self.features else None
        elif state_key is not None and state_key not in self.features:
            raise LeRobotError(info_path, f"state key {state_key!r} not in features {sorted(self.features)}")
        self.state_key = state_key
        if pose_key is not None and pose_key not in self.features:
            raise LeRobotError(info_path, f"pose key {pose_key!r} not in features {sorted(self.features)}")
        self.pose_key = pose_key
        self.tolerance_s = 0.25 / self.source_fps if tolerance_s is None else tolerance_s
        self.tasks = self._read_tasks()
        self._episodes = self._read_episodes()
        self.cache_size = cache_size
        self._cache: OrderedDict = OrderedDict()
        self._rows: OrderedDict = OrderedDict()  # small LRU of per-episode tabular data

    @property
    def views(self) -> list[str]:
        return list(self.cameras)

    def __len__(self) -> int:
        return len(self._episodes)

    # -- metadata ----------------------------------------------------------------------------------------------
    def _read_tasks(self) -> dict[int, str]:
        if self.version == "v3.0":
            path = self.root / "meta" / "tasks.parquet"
            if not path.exists():
                raise LeRobotError(path, "missing")
            table = pq.read_table(_regular(path))
            col = _task_column(table, path)
            pairs = zip(table["task_index"].to_pylist(), table[col].to_pylist(), strict=True)
            return {int(i): str(t) for i, t in pairs}
        rows = _read_jsonl(self.root / "meta" / "tasks.jsonl")
        return {int(r["task_index"]): r["task"] for r in rows}

    def _read_episodes(self) -> list[dict]:
        if self.version == "v3.0":
            files = sorted((self.root / "meta" / "episodes").glob("*/*.parquet"))
            if not files:
                raise LeRobotError(self.root / "meta" / "episodes", "no episode parquet files")
            rows = []
            for f in files:  # per-episode stats columns are large and unused here: skip them
                names = [n for n in pq.read_schema(_regular(f)).names if not n.startswith("stats/")]
                rows += [{**r, "_meta_file": f} for r in pq.read_table(f, columns=names).to_pylist()]
        else:
            rows = _read_jsonl(self.root / "meta" / "episodes.jsonl")
        return sorted(rows, key=lambda r: int(r["episode_index"]))

    def _data_path(self, ep: dict) -> Path:
        if self.version == "v3.0":
            return self._template("data_path", chunk_index=ep["data/chunk_index"], file_index=ep["data/file_index"])
        e = int(ep["episode_index"])
        return self._template("data_path", episode_chunk=e // int(self.info["chunks_size"]), episode_index=e)

    def _template(self, key: str, **fields) -> Path:
        """``info.json``'s path template ``key`` filled in, a file inside the dataset: an absolute template, one
        that climbs out (``..``) or an unknown placeholder is one line, never read (``/etc/hostname``) or a
        KeyError."""
        where = self.root / "meta" / "info.json"
        try:
            rel = self.info[key].format(**fields)
        except (KeyError, IndexError, ValueError, AttributeError) as e:
            raise LeRobotError(where, f"{key} {self.info.get(key)!r} does not fill in with {sorted(fields)} "
                                      f"({type(e).__name__}: {e}); restore info.json") from None
        try:
            return join_inside(self.root, rel)
        except UserError:
            raise LeRobotError(where, f"{key} {self.info[key]!r} names a file outside the dataset; restore "
                                      "info.json (paths there are relative to the dataset)") from None

    def _video_segment(self, ep: dict, key: str) -> tuple[Path, float, float | None]:
        """(mp4 path, time of the episode's t=0 inside it, end time or None)."""
        if self.version != "v3.0":
            e = int(ep["episode_index"])
            path = self._template("video_path", episode_chunk=e // int(self.info["chunks_size"]), video_key=key,
                                  episode_index=e)
            if os.path.lexists(path):
                _regular(path)
            return path, 0.0, None
        col = f"videos/{key}/"
        if col + "chunk_index" not in ep or ep[col + "chunk_index"] is None:
            raise LeRobotError(ep["_meta_file"], f"episode {ep['episode_index']} has no '{col}*' columns "
                                                 f"for camera {key!r}")
        path = self._template("video_path", video_key=key, chunk_index=ep[col + "chunk_index"],
                              file_index=ep[col + "file_index"])
        if os.path.lexists(path):
            _regular(path)
        return path, float(ep[col + "from_timestamp"]), float(ep[col + "to_timestamp"])

    # -- tabular data ------------------------------------------------------------------------------------------
    def _read_rows(self, ep: dict, columns: list[str]) -> pa.Table:
        """This episode's rows of ``columns`` from its data parquet, validated against the episode's length."""
        path = self._data_path(ep)
        if not path.exists():
            raise LeRobotError(path, f"missing data file of episode {ep['episode_index']}")
        have = pq.read_schema(_regular(path)).names
        for c in columns:
            if c not in have:
                raise LeRobotError(path, f"column {c!r} missing (have {have})")
        cols = list(dict.fromkeys(columns + ["episode_index"]))
        if self.version == "v3.0":  # shared file: row-group statistics let pyarrow skip other episodes
            table = pq.read_table(path, columns=cols, filters=[("episode_index", "=", int(ep["episode_index"]))])
        else:
            table = pq.read_table(path, columns=cols)
        length = int(ep["length"])
        if table.num_rows != length:
            raise LeRobotError(path, f"inconsistent lengths: episode {ep['episode_index']} has {table.num_rows} "
                                     f"rows but its metadata says length {length}")
        return table

    def _tabular(self, i: int) -> dict:
        if i in self._rows:
            self._rows.move_to_end(i)
            return self._rows[i]
        ep = self._episode_row(i)
        cols = ["timestamp", self.action_key] + [k for k in (self.state_key, self.pose_key) if k]
        cols += [c for c in ("frame_index", "task_index", SUCCESS_KEY) if c in self.features]
        cols = list(dict.fromkeys(cols))
        table = self._read_rows(ep, cols)
        out = {c: _to_numpy(table[c]) for c in cols}
        if "frame_index" in out and not np.array_equal(out["frame_index"], np.arange(table.num_rows)):
            raise LeRobotError(self._data_path(ep), f"episode {ep['episode_index']}: frame_index is not 0..T-1")
        self._rows[i] = out
        while len(self._rows) > 4:
            self._rows.popitem(last=False)
        return out

    def _episode_row(self, i: int) -> dict:
        if not 0 <= i < len(self._episodes):
            raise IndexError(f"episode {i} out of range (dataset has {len(self._episodes)})")
        return self._episodes[i]

    def episode_index(self, i: int) -> int:
        """The dataset's episode_index of episode ``i`` (its position), read from the metadata alone."""
        return int(self._episode_row(i)["episode_index"])

    def episode(self, i: int) -> LeRobotEpisode:
        """Episode ``i`` (position in episode_index order), resampled to ``self.fps``; frames decode lazily."""
        ep, tab = self._episode_row(i), self._tabular(i)
        s = slice(None, None, self.stride)
        tasks = list(ep.get("tasks") or [])
        # The prompt is the task of the first frame (``tasks`` in episode metadata is an unordered set).
        if "task_index" in tab and len(tab["task_index"]):
            prompt = self.tasks.get(int(tab["task_index"][0]), tasks[0] if tasks else "")
        else:
            prompt = tasks[0] if tasks else ""
        state = tab[self.state_key][s].astype(np.float32) if self.state_key else None
        pose = tab[self.pose_key][s].astype(np.float32) if self.pose_key else None
        # over every recorded frame, not only those kept at self.fps: success is often marked on the last one alone
        # (LeRobot's evaluation reduces it with any, as evaluation/labels.py does)
        success = bool(np.asarray(tab[SUCCESS_KEY]).astype(bool).any()) if SUCCESS_KEY in tab else None
        return LeRobotEpisode(self, i, int(ep["episode_index"]), tab["timestamp"][s],
                              tab[self.action_key][s].astype(np.float32), state, prompt, tasks, pose, success)

    # -- frames ------------------------------------------------------------------------------------------------
    def window(self, i: int, start: int, stop: int, views: list[str] | None = None) -> dict[str, np.ndarray]:
        """Frames ``start:stop`` (indices at ``self.fps``) of episode ``i``: view -> uint8 [L, H, W, 3]."""
        out = {}
        for view in views or self.views:
            if view not in self.cameras:
                raise LeRobotError(view, f"unknown view (views: {self.views})")
            key = (i, view, start, stop)
            if key in self._cache:
                self._cache.move_to_end(key)
                out[view] = self._cache[key]
                continue
            frames = self._decode(i, view, start, stop)
            frames.flags.writeable = False  # shared with the cache: callers must copy to modify
            if self.cache_size > 0:
                self._cache[key] = frames
                while len(self._cache) > self.cache_size:
                    self._cache.popitem(last=False)
            out[view] = frames
        return out

    def frame(self, i: int, t: int) -> dict[str, np.ndarray]:
        """Frame ``t`` of episode ``i``: view -> uint8 [H, W, 3]."""
        return {v: f[0] for v, f in self.window(i, t, t + 1).items()}

    def _decode(self, i: int, view: str, start: int, stop: int) -> np.ndarray:
        ep, tab = self._episode_row(i), self._tabular(i)
        rows = np.arange(len(tab["timestamp"]))[::self.stride][start:stop]
        key = self.cameras[view]
        if len(rows) == 0:
            h, w = self.features[key]["shape"][:2]
            return np.zeros((0, h, w, 3), np.uint8)
        if self.features[key]["dtype"] == "image":
            return self._decode_images(ep, key, rows)
        path, offset, end = self._video_segment(ep, key)
        if end is not None:
            dur = (len(tab["timestamp"])) / self.source_fps
            if abs((end - offset) - dur) > 1.0 / self.source_fps:
                raise LeRobotError(ep["_meta_file"], f"inconsistent lengths: episode {ep['episode_index']} camera "
                                                     f"{key!r} spans {end - offset:.3f} s of video but has "
                                                     f"{len(tab['timestamp'])} frames ({dur:.3f} s)")
        times = offset + tab["timestamp"][rows].astype(np.float64)
        return decode_video(path, times, self.tolerance_s)

    def _decode_images(self, ep: dict, key: str, rows: np.ndarray) -> np.ndarray:
        import cv2

        path = self._data_path(ep)
        column = self._read_rows(ep, [key])[key].take(pa.array(rows)).to_pylist()
        out = []
        for r, cell in zip(rows, column, strict=True):
            data = (cell or {}).get("bytes")
            if data is None and (cell or {}).get("path"):
                img_path = Path(cell["path"]) if os.path.isabs(cell["path"]) else self.root / cell["path"]
                data = img_path.read_bytes() if img_path.exists() else None
            if data is None:
                raise LeRobotError(path, f"image {key!r}, episode {ep['episode_index']} row {r}: no bytes and no file")
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if img is None:
                raise LeRobotError(path, f"image {key!r}, episode {ep['episode_index']} row {r}: cannot decode")
            out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        return np.stack(out)


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


MAX_SIDE = 4096  # pixels a side of an imported frame: a 20000 x 20000 one is 1.2 GB, per frame and view


def check_options(out, fps: float | None, image_size) -> None:
    """The numeric options of an import and its --out, in one line each before anything is read or written (``--fps
    0`` was a ZeroDivisionError, ``--image-size 0 -5`` a cv2 traceback after the store's dataset.json was written,
    which then refused the corrected rerun)."""
    from sc3_jax.core.validate import in_range, out_dir

    if fps is not None:
        in_range("--fps", fps, 1e-3, 10_000, "frames per second")
    for side in image_size or ():
        in_range("--image-size", side, 1, MAX_SIDE, "pixels a side")
    if image_size is not None and len(image_size) != 2:
        raise UserError(f"--image-size {' '.join(map(str, image_size))}: expected H W")
    out_dir(out, "--out")


def _stride(source_fps: float, fps: float | None, where: Path) -> int:
    if fps is None:
        return 1
    ratio = source_fps / float(fps)
    k = round(ratio)
    if k < 1 or not math.isclose(ratio, k, rel_tol=1e-6):
        raise LeRobotError(where, f"fps {fps} cannot be reached from the dataset's fps {source_fps:g} by "
                                  f"integer subsampling (ratio {ratio:.4g})")
    return int(k)


def _camera_map(features: dict, views, where: Path) -> dict[str, str]:
    cameras = [k for k, f in features.items() if f.get("dtype") in ("video", "image")]
    if views is None:
        mapping = {view_name(k): k for k in cameras}
    else:  # feature keys as they are, bare names are under observation.images.
        pairs = views.items() if isinstance(views, dict) else ((view_name(v), v) for v in views)
        mapping = {view: key if key in features else IMAGE_PREFIX + key for view, key in pairs}
    for view, key in mapping.items():
        if not is_safe(view):  # the view becomes a file name of the store we write: nothing outside it
            raise LeRobotError(where, f"camera {key!r} gives the view name {view!r}, which cannot be a file name "
                                      f"(only {ALLOWED}): rename it: --views NAME={key}")
        if key not in cameras:
            raise LeRobotError(where, f"camera {key!r} (view {view!r}) not found; cameras: {cameras}")
    if not mapping:
        raise LeRobotError(where, "dataset has no camera features (dtype video or image)")
    return mapping


def _regular(path: Path) -> Path:
    """``path`` if it is a regular file (a link to one is followed: a dataset in the Hugging Face cache is links
    into its blobs), else one line: a directory there was pyarrow's OSError traceback, a FIFO hung the import."""
    return regular_file(path, "restore the dataset's file from its source")


def _task_column(table: pa.Table, where: Path) -> str:
    """tasks.parquet keeps the task string as the pandas index: find which column holds it."""
    meta = (table.schema.metadata or {}).get(b"pandas")
    if meta:
        for c in json.loads(meta).get("index_columns", []):
            if isinstance(c, str) and c in table.column_names:
                return c
    for c in ("task", "__index_level_0__"):
        if c in table.column_names:
            return c
    raise LeRobotError(where, f"no task column (have {table.column_names})")


def _read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        raise LeRobotError(path, "missing")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _to_numpy(col: pa.ChunkedArray) -> np.ndarray:
    """A scalar column -> [N]; a (fixed-size) list column -> [N, D]."""
    col = col.combine_chunks()
    if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
        n = len(col)
        values = col.flatten().to_numpy(zero_copy_only=False)
        return values.reshape(n, -1) if n else values.reshape(0, 0)
    return col.to_numpy(zero_copy_only=False)


# -- conversion into our episode store ---------------------------------------------------------------------------
def import_lerobot(root: str | os.PathLike, out: str | os.PathLike, views=None, wrist_views=None,
                   fps: float | None = None, image_size: tuple[int, int] | None = None, action_key: str = "action",
                   pose_key: str | None = "observation.state", allow_missing_pose: bool = False,
                   progress: bool = False, *, action_space: str | None = None,
                   action_names: list[str] | None = None, action_targets: list[int] | None = None,
                   state_key: str | None = _OPTIONAL, episodes=None,  # type: ignore[assignment]
                   id_prefix: str = "") -> dict:
    """Convert the LeRobot dataset at ``root`` into an episode store at ``out``.

    The action space (``data/action_space.py``): ``action_space`` ("delta_ee", "absolute" or "velocity") with
    ``action_names`` (default: the feature's own names) and, for velocities, ``action_targets`` (indices of
    position-target dimensions such as a gripper); else our own export's ``sc3_action_space`` entry in info.json;
    else, for 7-D actions, the simulated benchmark's delta_ee (how stores were imported before declarations).
    Other actions without a declaration are refused (one line saying what to pass).

    ``pose_key``: a 7-D feature that becomes our ``ee_pose`` (x, y, z, rotation vector, gripper). delta_ee actions
    need one unless ``allow_missing_pose`` (then the store has no ee_pose: no pseudo-actions, motion relative to the
    start); for other action spaces it is optional (used where it names a 7-D feature other than the state).
    ``state_key``: the proprioceptive state feature of any size (default ``observation.state`` when present and not
    already the ee_pose; None: none), stored as ``state``. ``image_size`` resizes every view (our store has one size
    for all views). A ``next.success`` feature becomes each episode's meta ``"labels": {"success": any frame's}``
    (the real outcomes ``sc3 sweep episodes --real STORE`` reads). ``episodes``: the episode_index values to import (a
    container; None: all), so that one dataset gives a training store and a held-out one. Episodes are named
    ``{id_prefix}lerobot{episode_index:06d}``; existing ones are skipped (resumable). One prefix holds one dataset: a
    lab's several recording sessions go into one store under a prefix each (``id_prefix``: letters, digits, ``_``,
    ``-``).
    """
    if not re.fullmatch(r"[A-Za-z0-9_-]*", id_prefix):
        raise LeRobotError(out, f"id prefix {id_prefix!r}: letters, digits, '_' and '-' only (it names folders)")
    check_options(out, fps, image_size)
    from .action_space import ActionSpace, names_of
    from .episodes import Episode, EpisodeStore

    src = LeRobotEpisodes(root, views=views, wrist_views=wrist_views, fps=fps, action_key=action_key,
                          state_key=None)
    feats, info_path = src.features, Path(root) / "meta" / "info.json"
    chosen = [i for i in range(len(src)) if episodes is None or src.episode_index(i) in episodes]
    if not chosen:  # nothing would be imported, yet the command would say "train on it"
        have = [src.episode_index(i) for i in range(len(src))]
        raise LeRobotError(root, f"--episodes selects none of its {len(have)} episodes (episode_index "
                                 f"{min(have, default=0)}..{max(have, default=-1)})")
    dim = int(np.prod(feats[action_key]["shape"]))
    declared = src.info.get(INFO_ACTION_SPACE)
    if action_space is not None:
        space = ActionSpace(action_space, dim, tuple(action_names or names_of(feats[action_key].get("names"), dim)),
                            tuple(action_targets or ()))
    elif declared is not None:
        space = ActionSpace.from_dict(declared, dim, f"{info_path}: {INFO_ACTION_SPACE}")
    elif dim == 7:
        space = ActionSpace("delta_ee", 7)
    else:
        raise LeRobotError(info_path, f"{dim}-D {action_key!r} and no action-space declaration: pass action_space "
                                      f"'absolute' (position targets), 'velocity' or 'delta_ee'")
    is_pose = lambda k: k in feats and list(feats[k]["shape"]) == [7]  # noqa: E731
    if state_key is _OPTIONAL:
        state_key = "observation.state" if "observation.state" in feats else None
        if space.kind == "delta_ee" and state_key == pose_key and is_pose(pose_key):
            state_key = None  # the benchmark's layout: observation.state is the pose
    elif state_key is not None and state_key not in feats:
        raise LeRobotError(info_path, f"state key {state_key!r} not in features {sorted(feats)}")
    has_pose = is_pose(pose_key) and (space.kind == "delta_ee" or pose_key != state_key)
    if space.kind == "delta_ee" and not has_pose and not allow_missing_pose:
        shape = feats[pose_key]["shape"] if pose_key in feats else "missing"
        raise LeRobotError(pose_key, f"our ee_pose needs a 7-D feature, this one is {shape}; pass another pose "
                                     f"key or allow_missing_pose")
    src.pose_key, src.state_key = (pose_key if has_pose else None), state_key
    state_dim = int(np.prod(feats[state_key]["shape"])) if state_key else None
    state_names = (names_of(feats[state_key].get("names"), state_dim) or None) if state_key else None
    sizes = {tuple(feats[k]["shape"][:2]) for k in src.cameras.values()}
    if image_size is None and len(sizes) > 1:
        raise LeRobotError(root, f"cameras have different sizes {sorted(sizes)}: pass image_size to resize them")
    size = tuple(image_size) if image_size is not None else sizes.pop()
    fps_out = int(src.fps) if float(src.fps).is_integer() else src.fps  # keep "fps": 20 as our stores write it
    store = EpisodeStore(out, views=src.views, fps=fps_out, image_size=size, create=True, action_space=space,
                         state_dim=state_dim, state_names=state_names, has_pose=has_pose)
    source = str(Path(root).resolve())
    written = skipped = labelled = 0
    short: list[int] = []
    with locks.hold(store.root, "import"):  # two imports into one store would race on its episodes
        _check_same_source(store, source, id_prefix, {src.episode_index(i) for i in chosen})
        for i in chosen:
            ep = src.episode(i)
            eid = f"{id_prefix}lerobot{ep.episode_index:06d}"
            if eid in store:
                skipped += 1
                continue
            if ep.length < MIN_EPISODE_FRAMES:  # no training window and no initial condition can come of it
                short.append(ep.episode_index)
                if progress:
                    print(f"  skipped episode {ep.episode_index}: {ep.length} frame(s), fewer than "
                          f"{MIN_EPISODE_FRAMES}", flush=True)
                continue
            frames = {v: _resize(f, size) for v, f in ep.frames.items()}
            meta = {"source": "lerobot", "lerobot_root": source, "episode_index": ep.episode_index,
                    "tasks": ep.tasks, "source_fps": src.source_fps, "camera_keys": src.cameras,
                    "wrist_views": list(src.wrist_views), "timestamps": ep.timestamps.tolist(),
                    "ee_pose_source": pose_key if has_pose else "none", "state_source": state_key or "none"}
            if ep.success is not None:  # the real outcome, so that `sc3 sweep episodes --real STORE` needs no LeRobot source
                meta[LABELS_FIELD] = {"success": ep.success}
                labelled += 1
            store.write(Episode(eid, frames, ep.actions.reshape(ep.length, dim), ep.pose, ep.prompt, meta,
                                None if ep.state is None else ep.state.reshape(ep.length, state_dim)))
            written += 1
            if progress:
                print(f"  {eid}: {ep.length} frames", flush=True)
    return {"out": str(out), "written": written, "skipped": skipped, "too_short": short, "views": src.views,
            "fps": fps_out, "action_space": space.to_dict(), "state_dim": state_dim, "ee_pose": has_pose,
            "success_labels": labelled}  # of the episodes written: those whose meta holds next.success


def _check_same_source(store, source: str, prefix: str, indices: set[int]) -> None:
    """Importing dataset B into a store made from dataset A under the same id prefix would skip B's episodes as
    "already there" (their ids are episode indices) and keep A's; importing A again under another prefix would hold
    its episodes twice. Both refused, naming the store's source and prefix: duplicates are found by what was
    imported (source and episode_index), not by their names."""
    from sc3_jax.core import atomic

    held = []  # (id prefix, LeRobot root, episode_index, id) of every imported episode of the store
    for eid in store.episode_ids():
        m = re.fullmatch(r"(.*)lerobot(\d+)", eid)
        if m is not None:
            meta = atomic.read_json(store.root / eid / "meta.json", "restore it (the episode's metadata)")
            if meta.get("source") == "lerobot":
                held.append((m[1], meta.get("lerobot_root"), meta.get("episode_index"), eid))
    for pre, came, _, _ in held:
        if pre == prefix and came not in (None, source):
            raise LeRobotError(store.root, f"holds episodes imported from {came}, not from {source}"
                                           f"{' under this prefix' if prefix else ''}: import into another --out or "
                                           "under another --id-prefix")
    for pre, came, index, eid in held:
        if pre != prefix and came == source and index in indices:
            raise LeRobotError(store.root, f"holds episode {index} of {source} already, as {eid} (id prefix "
                                           f"{pre!r}): importing it again under {prefix!r} would give it twice; "
                                           f"resume with --id-prefix {pre!r}")


def _resize(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if tuple(frames.shape[1:3]) == tuple(size):
        return np.ascontiguousarray(frames)
    import cv2

    return np.stack([cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_AREA) for f in frames])
