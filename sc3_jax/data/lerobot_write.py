"""Write LeRobot datasets (v3.0, the current layout, or v2.1) with pyarrow and PyAV, and export our episode store.

Why a writer of our own: the simulated benchmark's demonstrations should load in anyone's LeRobot tooling, and the
reader's tests need datasets in both layouts and both codecs without installing ``lerobot`` (which pins old
torch/numpy). What we write follows LeRobot's conventions:

* data parquet columns ``observation.state``, ``action`` (fixed-size float32 lists), cameras of ``"dtype":
  "image"`` as ``struct<bytes, path>`` PNGs, then ``timestamp`` (= frame_index / fps), ``frame_index``,
  ``episode_index``, ``index`` (global row), ``task_index``; a feature of one value per frame (``"shape": [1]``,
  e.g. ``next.reward``, ``next.success``) is a plain column, not a list;
* v3.0 packs ``episodes_per_file`` episodes into one data parquet and one mp4 per camera; an episode's segment of
  the mp4 is ``[from_timestamp, to_timestamp)`` in ``meta/episodes/chunk-000/file-000.parquet``;
* v2.1 writes one parquet and one mp4 per camera per episode, plus ``meta/episodes.jsonl`` / ``tasks.jsonl`` /
  ``episodes_stats.jsonl``;
* ``meta/stats.json``: per feature ``mean/std/min/max/count``; camera stats are per channel on [0, 1] pixels with
  shape [3, 1, 1], like LeRobot's.

Videos use every frame's pts = frame number at time base 1/fps, keyframes every 2 frames (LeRobot's ``g=2``:
cheap random access) and yuv420p. The dataset is built in a temporary directory and renamed into place.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from collections.abc import Iterable, Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from sc3_jax.core import atomic
from .action_space import DELTA_EE_NAMES
from .action_space import POSE_NAMES as _POSE_NAMES
from .lerobot import ENVIRONMENT_STATE_KEY, IMAGE_PREFIX, INFO_ACTION_SPACE

VERSIONS = ("v3.0", "v2.1")
CHUNKS_SIZE = 1000
V3_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V3_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V2_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V2_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
ACTION_NAMES = list(DELTA_EE_NAMES)  # our delta end-effector action
POSE_NAMES = list(_POSE_NAMES)  # our ee_pose
POSE_KEY = "observation.ee_pose"  # where an ee_pose goes when observation.state holds another state
_INDEX_COLUMNS = ("frame_index", "episode_index", "index", "task_index")


@dataclasses.dataclass
class RawEpisode:
    """One episode in LeRobot terms: camera feature key -> uint8 [T, H, W, 3], action [T, D], state [T, S], and
    any other vector features (feature key -> [T, n], e.g. ``observation.ee_pose``; float32, or bool for a bool
    array such as ``next.success`` [T, 1])."""

    frames: dict[str, np.ndarray]
    action: np.ndarray
    task: str
    state: np.ndarray | None = None
    vectors: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def vector_features(self) -> list[tuple[str, np.ndarray | None]]:
        return [("observation.state", self.state), ("action", self.action), *self.vectors.items()]


# -- video ------------------------------------------------------------------------------------------------------
def av1_encoder() -> str | None:
    """The AV1 encoder this PyAV build has (SVT-AV1 preferred: much faster than libaom), or None."""
    import av

    for name in ("libsvtav1", "libaom-av1"):
        with contextlib.suppress(Exception):  # unknown name, or a decoder only
            return av.codec.Codec(name, "w").name
    return None


def _encoder(codec: str, crf: int | None) -> tuple[str, dict[str, str]]:
    if codec == "h264":  # crf 18: visually lossless, our frames are small so files stay small
        return "libx264", {"crf": str(18 if crf is None else crf), "g": "2"}
    if codec == "av1":
        name = av1_encoder()
        if name is None:
            raise RuntimeError("this PyAV build has no AV1 encoder (libsvtav1 or libaom-av1): use --codec h264")
        opts = {"crf": str(30 if crf is None else crf), "g": "2"}  # LeRobot's default AV1 quality
        if name == "libsvtav1":
            os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its whole config to stderr otherwise
            opts["preset"] = "8"
        else:
            opts["cpu-used"] = "8"
        return name, opts
    raise ValueError(f"unknown codec {codec!r} (h264 or av1)")


class _VideoFile:
    """An mp4 that episodes are appended to; returns each episode's [from, to) time segment."""

    def __init__(self, path: Path, codec: str, crf: int | None, fps: int, height: int, width: int):
        import av

        if height % 2 or width % 2:
            raise ValueError(f"{path}: yuv420p video needs even frame sizes, got {height}x{width}")
        path.parent.mkdir(parents=True, exist_ok=True)
        name, opts = _encoder(codec, crf)
        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream(name, rate=fps, options=opts)
        self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, "yuv420p"
        self.time_base, self.n, self.fps = Fraction(1, fps), 0, fps
        self.av = av

    def add(self, frames: np.ndarray) -> tuple[float, float]:
        start = self.n
        for img in frames:
            frame = self.av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            frame.pts, frame.time_base = self.n, self.time_base
            self.container.mux(self.stream.encode(frame))
            self.n += 1
        return start / self.fps, self.n / self.fps

    def close(self) -> None:
        self.container.mux(self.stream.encode(None))
        self.container.close()


# -- tables and stats -------------------------------------------------------------------------------------------
def _dtype(x: np.ndarray) -> str:
    return "bool" if np.asarray(x).dtype == bool else "float32"


def _vector(x: np.ndarray, feature: dict) -> pa.Array:
    """A [T, n] feature's column: one value per row where its shape is [1] (as LeRobot's ``datasets`` features store
    it: a ``Value``, which LeRobot reads back as [1]), else a fixed-size list per row."""
    x = np.asarray(x, np.dtype(feature["dtype"]))
    if feature["shape"] == [1]:
        return pa.array(x.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])


def _png(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


def _stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per-dimension stats over axis 0 (float64 so that aggregation over episodes stays exact enough)."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    return {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0), "count": np.array([len(x)])}


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    s = _stats(frames.reshape(-1, 3) / 255.0)  # per channel; count is the number of frames, as in LeRobot
    return {**{k: v.reshape(3, 1, 1) for k, v in s.items() if k != "count"}, "count": np.array([len(frames)])}


def _aggregate(per_episode: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Pooled stats: weighted mean, variance = mean within-episode variance + variance of episode means."""
    n = np.array([s["count"][0] for s in per_episode], np.float64)
    w = (n / n.sum()).reshape(-1, *[1] * per_episode[0]["mean"].ndim)
    means = np.stack([s["mean"] for s in per_episode])
    mean = (w * means).sum(0)
    var = (w * (np.stack([s["std"] for s in per_episode]) ** 2 + (means - mean) ** 2)).sum(0)
    return {"min": np.min([s["min"] for s in per_episode], 0), "max": np.max([s["max"] for s in per_episode], 0),
            "mean": mean, "std": np.sqrt(var), "count": np.array([int(n.sum())])}


def _jsonable(stats: dict[str, dict[str, np.ndarray]]) -> dict:
    return {k: {s: np.asarray(v).tolist() for s, v in st.items()} for k, st in stats.items()}


# -- the writer -------------------------------------------------------------------------------------------------
def write_lerobot(out: str | os.PathLike, episodes: Iterable[RawEpisode], fps: int, version: str = "v3.0",
                  codec: str = "h264", image_dtype: str = "video", crf: int | None = None,
                  episodes_per_file: int = 1000, names: dict[str, list[str]] | None = None,
                  robot_type: str = "unknown", overwrite: bool = False, info: dict | None = None) -> dict:
    """Write ``episodes`` as a LeRobot dataset at ``out``. ``image_dtype``: "video" (mp4) or "image" (PNG in parquet).
    ``info``: extra ``meta/info.json`` entries (e.g. our action-space declaration, ``INFO_ACTION_SPACE``).

    Returns a summary dict (episodes, frames, tasks, path).
    """
    if version not in VERSIONS:
        raise ValueError(f"cannot write codebase_version {version!r} (supported: {', '.join(VERSIONS)})")
    if image_dtype not in ("video", "image"):
        raise ValueError(f"image_dtype must be 'video' or 'image', got {image_dtype!r}")
    if float(fps) != int(fps):
        raise ValueError(f"LeRobot datasets have an integer fps, got {fps}")
    fps, out = int(fps), Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty (pass overwrite=True)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic.temp_dir(out)
    try:
        summary = _Writer(tmp, fps, version, codec, image_dtype, crf, episodes_per_file, names or {},
                          robot_type, info or {}).run(iter(episodes))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {**summary, "out": str(out)}


class _Writer:
    def __init__(self, root: Path, fps: int, version: str, codec: str, image_dtype: str, crf: int | None,
                 episodes_per_file: int, names: dict, robot_type: str, extra_info: dict):
        self.root, self.fps, self.version, self.codec = root, fps, version, codec
        self.image_dtype, self.crf, self.per_file = image_dtype, crf, max(1, episodes_per_file)
        self.names, self.robot_type, self.extra_info = names, robot_type, extra_info
        self.tasks: dict[str, int] = {}
        self.rows: list[dict] = []  # per-episode metadata
        self.stats: list[dict] = []  # per-episode stats
        self.total = 0
        self.group, self.pq_writer, self.videos = -1, None, {}

    def run(self, episodes: Iterator[RawEpisode]) -> dict:
        first = next(episodes, None)
        if first is None:
            raise ValueError("no episodes to write")
        self.features = self._features(first)
        self.cameras = [k for k, f in self.features.items() if f["dtype"] in ("video", "image")]
        self.schema = self._schema()
        self._write_episode(0, first)
        for e, ep in enumerate(episodes, start=1):
            self._write_episode(e, ep)
        self._close_group()
        self._write_meta()
        return {"episodes": len(self.rows), "frames": self.total, "tasks": len(self.tasks)}

    def _features(self, ep: RawEpisode) -> dict:
        feats = {}
        for key, x in ep.vector_features():
            if x is not None:
                d = np.asarray(x).shape[1]
                feats[key] = {"dtype": _dtype(x), "shape": [d], "names": self.names.get(key, [f"{key}_{i}"
                                                                                           for i in range(d)])}
        for key, f in ep.frames.items():
            h, w = f.shape[1:3]
            feats[key] = {"dtype": self.image_dtype, "shape": [h, w, 3], "names": ["height", "width", "channels"]}
            if self.image_dtype == "video":
                feats[key]["info"] = {"video.height": h, "video.width": w, "video.codec": self.codec,
                                      "video.pix_fmt": "yuv420p", "video.is_depth_map": False,
                                      "video.fps": self.fps, "video.channels": 3, "has_audio": False}
        feats["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
        feats.update({k: {"dtype": "int64", "shape": [1], "names": None} for k in _INDEX_COLUMNS})
        return feats

    def _schema(self) -> pa.Schema:
        fields, hf = [], {}
        for key, f in self.features.items():
            if f["dtype"] == "video":
                continue
            if f["dtype"] == "image":
                fields.append(pa.field(key, pa.struct([("bytes", pa.binary()), ("path", pa.string())])))
                hf[key] = {"_type": "Image"}
            elif f["shape"] == [1]:
                fields.append(pa.field(key, pa.from_numpy_dtype(np.dtype(f["dtype"]))))
                hf[key] = {"dtype": f["dtype"], "_type": "Value"}
            else:
                fields.append(pa.field(key, pa.list_(pa.from_numpy_dtype(np.dtype(f["dtype"])), f["shape"][0])))
                hf[key] = {"feature": {"dtype": f["dtype"], "_type": "Value"}, "length": f["shape"][0],
                           "_type": "Sequence"}
        # Hugging Face `datasets` reads its feature types (e.g. Image) from this schema metadata.
        return pa.schema(fields, metadata={"huggingface": json.dumps({"info": {"features": hf}})})

    def _check(self, e: int, ep: RawEpisode) -> int:
        length = len(ep.action)
        if sorted(ep.frames) != sorted(self.cameras):
            raise ValueError(f"episode {e}: cameras {sorted(ep.frames)}, expected {sorted(self.cameras)}")
        for key, x in [*ep.vector_features(), *ep.frames.items()]:
            if key in self.features and (x is None or len(x) != length or
                                         list(np.shape(x)[1:]) != self.features[key]["shape"]):
                raise ValueError(f"episode {e}, {key}: shape {np.shape(x)} does not match {length} actions / "
                                 f"feature shape {self.features[key]['shape']}")
        return length

    def _write_episode(self, e: int, ep: RawEpisode) -> None:
        length = self._check(e, ep)
        task_index = self.tasks.setdefault(ep.task, len(self.tasks))
        frame_index = np.arange(length)
        columns = {"timestamp": (frame_index / self.fps).astype(np.float32), "frame_index": frame_index,
                   "episode_index": np.full(length, e), "index": self.total + frame_index,
                   "task_index": np.full(length, task_index)}
        stats = {k: _stats(v) for k, v in columns.items()}
        arrays = []
        for field in self.schema:
            key = field.name
            if key in columns:
                arrays.append(pa.array(columns[key], field.type))
            elif key in self.cameras:  # image dtype
                arrays.append(pa.array([{"bytes": _png(img), "path": None} for img in ep.frames[key]], field.type))
            else:
                x = dict(ep.vector_features())[key]
                arrays.append(_vector(x, self.features[key]))
                stats[key] = _stats(x)
        for key in self.cameras:
            stats[key] = _image_stats(ep.frames[key])
        table = pa.Table.from_arrays(arrays, schema=self.schema)
        row = {"episode_index": e, "tasks": [ep.task], "length": length}
        if self.version == "v3.0":
            row.update(self._append_v3(e, ep, table))
            row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        else:
            self._write_v2(e, ep, table)
        row["dataset_from_index"], row["dataset_to_index"] = self.total, self.total + length
        self.rows.append(row)
        self.stats.append(stats)
        self.total += length

    def _append_v3(self, e: int, ep: RawEpisode, table: pa.Table) -> dict:
        group = e // self.per_file
        chunk, file = divmod(group, CHUNKS_SIZE)
        if group != self.group:
            self._close_group()
            self.group = group
            path = self.root / V3_DATA_PATH.format(chunk_index=chunk, file_index=file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self.pq_writer = pq.ParquetWriter(path, self.schema)
            if self.image_dtype == "video":
                self.videos = {k: _VideoFile(self.root / V3_VIDEO_PATH.format(video_key=k, chunk_index=chunk,
                                                                              file_index=file),
                                             self.codec, self.crf, self.fps, *ep.frames[k].shape[1:3])
                               for k in self.cameras}
        self.pq_writer.write_table(table)  # one row group per episode: readers can skip the others
        row = {"data/chunk_index": chunk, "data/file_index": file}
        for key, video in self.videos.items():
            start, end = video.add(ep.frames[key])
            row.update({f"videos/{key}/chunk_index": chunk, f"videos/{key}/file_index": file,
                        f"videos/{key}/from_timestamp": start, f"videos/{key}/to_timestamp": end})
        return row

    def _close_group(self) -> None:
        if self.pq_writer is not None:
            self.pq_writer.close()
        for video in self.videos.values():
            video.close()
        self.pq_writer, self.videos = None, {}

    def _write_v2(self, e: int, ep: RawEpisode, table: pa.Table) -> None:
        chunk = e // CHUNKS_SIZE
        path = self.root / V2_DATA_PATH.format(episode_chunk=chunk, episode_index=e)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        if self.image_dtype == "video":
            for key in self.cameras:
                video = _VideoFile(self.root / V2_VIDEO_PATH.format(episode_chunk=chunk, video_key=key,
                                                                    episode_index=e),
                                   self.codec, self.crf, self.fps, *ep.frames[key].shape[1:3])
                video.add(ep.frames[key])
                video.close()

    def _write_meta(self) -> None:
        meta = self.root / "meta"
        meta.mkdir(exist_ok=True)
        n_eps, videos = len(self.rows), self.image_dtype == "video"
        info = {"codebase_version": self.version, "robot_type": self.robot_type, "total_episodes": n_eps,
                "total_frames": self.total, "total_tasks": len(self.tasks), "chunks_size": CHUNKS_SIZE,
                "fps": self.fps, "splits": {"train": f"0:{n_eps}"}}
        stats = {k: _aggregate([s[k] for s in self.stats]) for k in self.features}
        atomic.write_json(meta / "stats.json", _jsonable(stats))
        if self.version == "v3.0":
            info.update({"data_files_size_in_mb": 100, "video_files_size_in_mb": 500, "data_path": V3_DATA_PATH,
                         "video_path": V3_VIDEO_PATH if videos else None})
            task_table = pa.table({"task_index": pa.array(list(self.tasks.values()), pa.int64()),
                                   "task": list(self.tasks)})
            # pandas metadata makes `pd.read_parquet` give the task string as the index, as LeRobot expects.
            pandas_meta = {"index_columns": ["task"], "column_indexes": [], "columns": [
                {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
                 "metadata": None},
                {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
                 "metadata": None}]}
            pq.write_table(task_table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)}),
                           meta / "tasks.parquet")
            rows = [{**r, **{f"stats/{k}/{s}": np.asarray(v).tolist() for k, st in stats_.items()
                             for s, v in st.items()}} for r, stats_ in zip(self.rows, self.stats, strict=True)]
            (meta / "episodes" / "chunk-000").mkdir(parents=True)
            pq.write_table(pa.Table.from_pylist(rows), meta / "episodes" / "chunk-000" / "file-000.parquet")
        else:
            info.update({"total_chunks": (n_eps - 1) // CHUNKS_SIZE + 1,
                         "total_videos": n_eps * len(self.cameras) if videos else 0,
                         "data_path": V2_DATA_PATH, "video_path": V2_VIDEO_PATH if videos else None})
            _write_jsonl(meta / "tasks.jsonl", [{"task_index": i, "task": t} for t, i in self.tasks.items()])
            _write_jsonl(meta / "episodes.jsonl", [{k: r[k] for k in ("episode_index", "tasks", "length")}
                                                   for r in self.rows])
            _write_jsonl(meta / "episodes_stats.jsonl", [{"episode_index": r["episode_index"], "stats": _jsonable(s)}
                                                         for r, s in zip(self.rows, self.stats, strict=True)])
        info["features"] = self.features
        atomic.write_json(meta / "info.json", {**info, **self.extra_info}, indent=4)


def _write_jsonl(path: Path, rows: list[dict]) -> None:
    atomic.write_text(path, "".join(json.dumps(r) + "\n" for r in rows))


# -- our episode store -> LeRobot -------------------------------------------------------------------------------
def export_store(store, out: str | os.PathLike, version: str = "v3.0", codec: str = "h264",
                 image_dtype: str = "video", crf: int | None = None, views: list[str] | None = None,
                 robot_type: str = "sc3_sim", overwrite: bool = False) -> dict:
    """Export an episode store (path or EpisodeStore): ``actions`` -> ``action``, the recorded ``state`` ->
    ``observation.state`` (a store without one: its ``ee_pose`` there, as the simulated benchmark's), an ``ee_pose``
    beside a state -> ``observation.ee_pose``, an ``object_state`` -> ``observation.environment_state`` (with its
    names), view ``v`` -> ``observation.images.v``, prompt -> task, the action space -> ``info.json``
    ``sc3_action_space`` (import reads it back). Episodes go in sorted id order."""
    from .episodes import EpisodeStore

    store = store if isinstance(store, EpisodeStore) else EpisodeStore(store)
    views = list(views or store.views)

    def episodes() -> Iterator[RawEpisode]:
        for eid in store.episode_ids():
            ep = store.load(eid, mmap=True)
            state, extra = (ep.state, {POSE_KEY: ep.ee_pose} if store.has_pose else {}) if store.state_dim \
                else (ep.ee_pose, {})
            if store.object_state_dim:
                extra = {**extra, ENVIRONMENT_STATE_KEY: ep.object_state}
            yield RawEpisode({IMAGE_PREFIX + v: ep.frames[v] for v in views}, ep.actions, ep.prompt, state, extra)

    space = store.action_space
    names = {"action": list(space.names), POSE_KEY: POSE_NAMES,
             "observation.state": list(store.state_names) if store.state_dim else POSE_NAMES}
    if store.object_state_dim and store.object_state_names:
        names[ENVIRONMENT_STATE_KEY] = list(store.object_state_names)
    return write_lerobot(out, episodes(), store.fps, version=version, codec=codec, image_dtype=image_dtype, crf=crf,
                         names=names, robot_type=robot_type, overwrite=overwrite,
                         info={INFO_ACTION_SPACE: space.to_dict()})
