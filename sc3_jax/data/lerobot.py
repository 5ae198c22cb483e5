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

Video frames are decoded by ``lerobot_video.decode_video``; ``lerobot_import.import_lerobot`` converts a dataset into
our episode store.
"""
from __future__ import annotations

import functools
import json
import math
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError
from sc3_jax.core.safe_names import ALLOWED, is_safe, join_inside
from sc3_jax.core.validate import is_count, is_finite_number, json_object, regular_file
from sc3_jax.data.lerobot_error import LeRobotError
from sc3_jax.data.lerobot_video import decode_video

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
OPTIONAL = object()  # sentinel: "use observation.state if the dataset has it" (the importer's default too)
# LeRobot's per-frame state of the scene's objects (e.g. a block's position), our store's ``object_state``
ENVIRONMENT_STATE_KEY = "observation.environment_state"


def _parquet(read, path: Path, **kw):
    """``read(path, **kw)`` (``pq.read_table`` / ``pq.read_schema``) of a regular file of the dataset, a damaged one
    (cut short, not parquet) one line naming it: pyarrow's own message named no file."""
    try:
        return read(_regular(path), **kw)
    except (pa.ArrowException, OSError) as e:
        if isinstance(e, OSError) and e.errno is not None:
            raise  # a file that cannot be opened: the command layer says so
        said = " ".join(str(e).split())
        said = said.split("': ", 1)[-1] if said.startswith("Could not open") else said  # (its path, named already)
        raise LeRobotError(path, f"not a whole parquet file ({said[:160]}); restore it from the dataset's "
                                 "source") from None


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
                 pose: np.ndarray | None = None, success: bool | None = None,
                 object_state: np.ndarray | None = None):
        self._source, self.index, self.episode_index = source, index, episode_index
        self.timestamps, self.actions, self.state, self.pose = timestamps, actions, state, pose
        self.object_state = object_state  # [T, O] the objects' state (None: not read)
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
        is used when present. ``pose_key``: a column read as ``pose`` too (None: none). ``object_state_key``: a
        column read as ``object_state`` (None: none; e.g. ``observation.environment_state``).
    cache_size: how many decoded (episode, view, span) windows to keep, least recently used out first; 0 = none.
    tolerance_s: how far a decoded video frame may sit from the requested time (default a quarter frame period).
    """

    def __init__(self, root: str | os.PathLike, views: list[str] | dict[str, str] | None = None,
                 wrist_views: list[str] | None = None, fps: float | None = None, action_key: str = "action",
                 state_key: str | None = OPTIONAL, cache_size: int = 0,  # type: ignore[assignment]
                 tolerance_s: float | None = None, pose_key: str | None = None,
                 object_state_key: str | None = None):
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
        if state_key is OPTIONAL:
            state_key = "observation.state" if "observation.state" in self.features else None
        elif state_key is not None and state_key not in self.features:
            raise LeRobotError(info_path, f"state key {state_key!r} not in features {sorted(self.features)}")
        self.state_key = state_key
        if pose_key is not None and pose_key not in self.features:
            raise LeRobotError(info_path, f"pose key {pose_key!r} not in features {sorted(self.features)}")
        self.pose_key = pose_key
        if object_state_key is not None and object_state_key not in self.features:
            raise LeRobotError(info_path, f"object state key {object_state_key!r} not in features "
                                          f"{sorted(self.features)}")
        self.object_state_key = object_state_key
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
            table = _parquet(pq.read_table, path)
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
                names = [n for n in _parquet(pq.read_schema, f).names if not n.startswith("stats/")]
                rows += [{**r, "_meta_file": f} for r in _parquet(pq.read_table, f, columns=names).to_pylist()]
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
        have = _parquet(pq.read_schema, path).names
        for c in columns:
            if c not in have:
                raise LeRobotError(path, f"column {c!r} missing (have {have})")
        cols = list(dict.fromkeys(columns + ["episode_index"]))
        if self.version == "v3.0":  # shared file: row-group statistics let pyarrow skip other episodes
            table = _parquet(pq.read_table, path, columns=cols,
                             filters=[("episode_index", "=", int(ep["episode_index"]))])
        else:
            table = _parquet(pq.read_table, path, columns=cols)
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
        cols = ["timestamp", self.action_key] + [k for k in (self.state_key, self.pose_key, self.object_state_key)
                                                 if k]
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
        objects = tab[self.object_state_key][s].astype(np.float32) if self.object_state_key else None
        # over every recorded frame, not only those kept at self.fps: success is often marked on the last one alone
        # (LeRobot's evaluation reduces it with any, as evaluation/labels.py does)
        success = bool(np.asarray(tab[SUCCESS_KEY]).astype(bool).any()) if SUCCESS_KEY in tab else None
        return LeRobotEpisode(self, i, int(ep["episode_index"]), tab["timestamp"][s],
                              tab[self.action_key][s].astype(np.float32), state, prompt, tasks, pose, success,
                              objects)

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
