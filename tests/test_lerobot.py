"""LeRobot datasets: writing both layouts (v2.1, v3.0) with h264 / AV1 / PNG cameras, reading them back, the
reader's errors, and export -> import of the simulated benchmark's demonstrations."""
import json
import shutil

import numpy as np
import pytest

av = pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
pa = pytest.importorskip("pyarrow", reason="LeRobot support needs the [lerobot] extra (pyarrow)")
import pyarrow.parquet as pq  # noqa: E402

from sc3_jax.data.lerobot import LeRobotEpisodes  # noqa: E402
from sc3_jax.data.lerobot_error import LeRobotError  # noqa: E402
from sc3_jax.data.lerobot_import import import_lerobot  # noqa: E402
from sc3_jax.data.lerobot_write import RawEpisode, av1_encoder, write_lerobot  # noqa: E402

FPS = 20
LENGTHS = (12, 9, 15)
TASKS = ("pick the cup", "wipe the table", "pick the cup")
CAMS = ("observation.images.left", "observation.images.wrist")
MAX_MAE = 6.0  # mean absolute error in uint8 levels (6/255) allowed for lossy codecs on smooth frames


def _smooth(length: int, phase: float, size: int = 32) -> np.ndarray:
    """Smooth moving colour gradients: what lossy codecs reproduce well, so errors mean bugs, not compression."""
    t, y, x = np.meshgrid(np.arange(length), np.arange(size), np.arange(size), indexing="ij")
    return np.stack([120 + 60 * np.sin(x / 7 + t / 5 + phase), 120 + 60 * np.cos(y / 6 + t / 4 + phase),
                     80 + 3 * t + 0 * x], -1).astype(np.uint8)


def _episodes() -> list[RawEpisode]:
    rng = np.random.default_rng(0)
    return [RawEpisode({cam: _smooth(n, e + 2 * c) for c, cam in enumerate(CAMS)},
                       rng.normal(size=(n, 7)).astype(np.float32), TASKS[e], rng.normal(size=(n, 5)).astype(np.float32))
            for e, n in enumerate(LENGTHS)]


def _codec(codec: str) -> str:
    if codec == "av1" and av1_encoder() is None:
        pytest.skip("this PyAV build has no AV1 encoder (libsvtav1 or libaom-av1)")
    return codec


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """Writes each (version, codec) dataset once; tests that break a dataset copy it first."""
    made = {}

    def get(version: str, codec: str = "h264", images: str = "video"):
        key = (version, codec, images)
        if key not in made:
            made[key] = tmp_path_factory.mktemp("lerobot") / f"{version}_{codec}_{images}"
            write_lerobot(made[key], _episodes(), FPS, version=version, codec=_codec(codec), image_dtype=images)
        return made[key]
    return get


def _broken_copy(src, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(src, dst)
    return dst


# -- reading what we wrote ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
@pytest.mark.parametrize("codec", ["h264", "av1"])
def test_read_videos(datasets, version, codec):
    ds = LeRobotEpisodes(datasets(version, codec))
    assert len(ds) == 3 and ds.version == version and ds.fps == FPS
    assert ds.views == ["left", "wrist"] and ds.wrist_views == ("wrist",) and ds.third_person_views == ("left",)
    for i, raw in enumerate(_episodes()):
        ep = ds.episode(i)
        n = LENGTHS[i]
        np.testing.assert_array_equal(ep.actions, raw.action)
        np.testing.assert_array_equal(ep.state, raw.state)
        np.testing.assert_array_equal(ep.timestamps, (np.arange(n) / FPS).astype(np.float32))
        assert ep.prompt == TASKS[i] and ep.tasks == [TASKS[i]] and ep.length == n
        for view, cam in zip(ds.views, CAMS, strict=True):
            assert ep.frames[view].shape == (n, 32, 32, 3) and ep.frames[view].dtype == np.uint8
            assert np.abs(ep.frames[view].astype(float) - raw.frames[cam]).mean() < MAX_MAE, (view, i)


def test_v3_layout_packs_episodes_into_one_file(datasets):
    root = datasets("v3.0")
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_episodes"] == 3 and info["total_frames"] == sum(LENGTHS)
    assert info["features"]["observation.images.left"]["info"]["video.codec"] == "h264"
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()) == sorted(
        ["meta/info.json", "meta/stats.json", "meta/tasks.parquet", "meta/episodes/chunk-000/file-000.parquet",
         "data/chunk-000/file-000.parquet", *(f"videos/{c}/chunk-000/file-000.mp4" for c in CAMS)])
    eps = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    bounds = np.cumsum((0,) + LENGTHS)
    for e, row in enumerate(eps):
        assert (row["dataset_from_index"], row["dataset_to_index"]) == (bounds[e], bounds[e + 1])
        for cam in CAMS:  # consecutive segments of one mp4
            assert row[f"videos/{cam}/from_timestamp"] == pytest.approx(bounds[e] / FPS)
            assert row[f"videos/{cam}/to_timestamp"] == pytest.approx(bounds[e + 1] / FPS)
    with av.open(str(root / "videos" / CAMS[0] / "chunk-000" / "file-000.mp4")) as c:
        assert sum(1 for _ in c.decode(video=0)) == sum(LENGTHS)
    tasks = pq.read_table(root / "meta" / "tasks.parquet")  # task string is the pandas index, as in LeRobot
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    task_of = dict(zip(tasks["task"].to_pylist(), tasks["task_index"].to_pylist(), strict=True))
    assert task_of == {TASKS[0]: 0, TASKS[1]: 1}


def test_v21_layout(datasets):
    root = datasets("v2.1")
    assert (root / "data" / "chunk-000" / "episode_000002.parquet").exists()
    assert (root / "videos" / "chunk-000" / CAMS[1] / "episode_000001.mp4").exists()
    episodes = [json.loads(line) for line in (root / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert [e["length"] for e in episodes] == list(LENGTHS)
    stats = [json.loads(line) for line in (root / "meta" / "episodes_stats.jsonl").read_text().splitlines()]
    assert stats[1]["stats"]["action"]["count"] == [LENGTHS[1]]


@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_image_features_are_exact(datasets, version):
    root = datasets(version, images="image")
    ds = LeRobotEpisodes(root)
    data = next(root.glob("data/chunk-000/*.parquet"))
    col = pq.read_table(data, columns=[CAMS[0]])[CAMS[0]]
    assert col.type == pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    assert col[0].as_py()["bytes"][:8] == b"\x89PNG\r\n\x1a\n"
    for i, raw in enumerate(_episodes()):
        for view, cam in zip(ds.views, CAMS, strict=True):
            np.testing.assert_array_equal(ds.episode(i).frames[view], raw.frames[cam])


def test_random_access_and_window_cache(datasets):
    ds = LeRobotEpisodes(datasets("v3.0"), cache_size=2)
    full = ds.episode(2).frames
    w = ds.window(2, 5, 11)
    for view in ds.views:
        np.testing.assert_array_equal(w[view], full[view][5:11])
        assert not w[view].flags.writeable  # shared with the cache
    assert ds.window(2, 5, 11)["left"] is w["left"]  # served from the cache
    np.testing.assert_array_equal(ds.frame(1, 4)["wrist"], ds.episode(1).frames["wrist"][4])
    ds.window(0, 0, 2)  # two more windows per view evict the first
    assert ds.window(2, 5, 11)["left"] is not w["left"]
    assert ds.window(1, 3, 3)["left"].shape == (0, 32, 32, 3)


def test_fps_subsampling(datasets):
    root = datasets("v3.0")
    full, half = LeRobotEpisodes(root).episode(2), LeRobotEpisodes(root, fps=10).episode(2)
    assert half.fps == 10 and half.length == 8
    np.testing.assert_array_equal(half.timestamps, full.timestamps[::2])
    np.testing.assert_array_equal(half.actions, full.actions[::2])
    np.testing.assert_array_equal(half.state, full.state[::2])
    np.testing.assert_array_equal(half.frames["left"], full.frames["left"][::2])
    for fps in (15, 40):
        with pytest.raises(LeRobotError, match="cannot be reached .* integer subsampling"):
            LeRobotEpisodes(root, fps=fps)


def test_camera_mapping_and_columns(datasets):
    root = datasets("v2.1")
    ds = LeRobotEpisodes(root, views={"top": "observation.images.left", "hand": "wrist"}, wrist_views=["hand"],
                         state_key=None)
    assert ds.views == ["top", "hand"] and ds.wrist_views == ("hand",) and ds.third_person_views == ("top",)
    assert ds.cameras["hand"] == "observation.images.wrist"
    ep = ds.episode(0)
    assert ep.state is None and set(ep.frames) == {"top", "hand"}
    assert LeRobotEpisodes(root, views=["wrist"]).views == ["wrist"]


# -- errors ------------------------------------------------------------------------------------------------------
def test_error_missing_camera_and_columns(datasets):
    root = datasets("v3.0")
    with pytest.raises(LeRobotError, match=r"camera 'observation.images.top' \(view 'top'\) not found"):
        LeRobotEpisodes(root, views=["top"])
    with pytest.raises(LeRobotError, match="wrist view 'hand'"):
        LeRobotEpisodes(root, wrist_views=["hand"])
    with pytest.raises(LeRobotError, match="state key 'observation.joints'"):
        LeRobotEpisodes(root, state_key="observation.joints")
    with pytest.raises(LeRobotError, match="action key 'act'"):
        LeRobotEpisodes(root, action_key="act")


def test_error_unsupported_version(datasets, tmp_path):
    root = _broken_copy(datasets("v2.1"), tmp_path)
    info = json.loads((root / "meta" / "info.json").read_text())
    (root / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v1.6"}))
    with pytest.raises(LeRobotError, match=r"info.json: unsupported codebase_version 'v1.6'"):
        LeRobotEpisodes(root)
    with pytest.raises(LeRobotError, match="info.json: missing"):
        LeRobotEpisodes(tmp_path / "nothing")


def test_error_inconsistent_lengths(datasets, tmp_path):
    # episode metadata says 10 rows, the parquet has 9
    root = _broken_copy(datasets("v2.1"), tmp_path)
    path = root / "meta" / "episodes.jsonl"
    path.write_text(path.read_text().replace('"length": 9', '"length": 10'))
    with pytest.raises(LeRobotError, match=r"episode_000001.parquet: inconsistent lengths: episode 1 has 9 rows"):
        LeRobotEpisodes(root).episode(1)
    # the mp4 of episode 2 is shorter than its parquet
    eps, short = _episodes(), tmp_path / "short"
    last = RawEpisode({c: f[:10] for c, f in eps[2].frames.items()}, eps[2].action[:10], TASKS[2], eps[2].state[:10])
    write_lerobot(short, eps[:2] + [last], FPS, version="v2.1")
    broken = _broken_copy(datasets("v2.1"), tmp_path / "b")
    video = "videos/chunk-000/observation.images.left/episode_000002.mp4"
    shutil.copy(short / video, broken / video)
    with pytest.raises(LeRobotError, match="episode_000002.mp4: inconsistent lengths: video ends"):
        _ = LeRobotEpisodes(broken).episode(2).frames
    # v3.0: an episode's video segment disagrees with its number of frames
    root = _broken_copy(datasets("v3.0"), tmp_path / "v3")
    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    table = pq.read_table(path)
    col = f"videos/{CAMS[0]}/to_timestamp"
    to = table[col].to_numpy().copy()
    to[0] += 0.5
    pq.write_table(table.set_column(table.schema.get_field_index(col), col, pa.array(to)), path)
    with pytest.raises(LeRobotError, match="file-000.parquet: inconsistent lengths: episode 0 camera"):
        LeRobotEpisodes(root).window(0, 0, 2)


def test_error_undecodable_codec_and_missing_video(datasets, tmp_path):
    root = _broken_copy(datasets("v2.1"), tmp_path)
    video = root / "videos" / "chunk-000" / CAMS[0] / "episode_000000.mp4"
    # An mp4 whose sample entry names a codec FFmpeg has no decoder for (as AV1 is for builds without dav1d).
    video.write_bytes(video.read_bytes().replace(b"avc1", b"zzzz"))
    with pytest.raises(LeRobotError, match=r"episode_000000.mp4: codec .* cannot be decoded"):
        LeRobotEpisodes(root).window(0, 0, 1)
    video.unlink()
    with pytest.raises(LeRobotError, match="episode_000000.mp4: missing video file"):
        LeRobotEpisodes(root).window(0, 0, 1)


# -- export -> import of the simulated benchmark's demonstrations ------------------------------------------------
def test_sim_export_import_roundtrip(tmp_path):
    pytest.importorskip("mujoco")
    import sc3_jax.benchmarks.bussing  # noqa: F401
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.cli import main
    from sc3_jax.benchmarks.bussing.demos import generate_demos

    generate_demos(tmp_path / "demos", 2, seed=0, image_size=(64, 64), progress=False)
    assert main(["data", "export-lerobot", "--data", str(tmp_path / "demos"), "--out", str(tmp_path / "lr")]) == 0
    root = tmp_path / "lr"
    info = json.loads((root / "meta" / "info.json").read_text())
    src = EpisodeStore(tmp_path / "demos")
    eps = [src.load(e) for e in src.episode_ids()]
    total = sum(e.length for e in eps)
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20 and info["total_frames"] == total
    assert info["features"]["observation.state"]["names"][:3] == ["x", "y", "z"]
    assert {f"observation.images.{v}" for v in src.views} <= set(info["features"])
    stats = json.loads((root / "meta" / "stats.json").read_text())
    actions = np.concatenate([e.actions for e in eps])
    for key in ("action", "observation.state", "observation.images.left", "timestamp"):
        assert set(stats[key]) == {"mean", "std", "min", "max", "count"} and stats[key]["count"] == [total]
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), atol=1e-6)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(0), atol=1e-6)
    assert np.shape(stats["observation.images.left"]["mean"]) == (3, 1, 1)

    assert main(["data", "import-lerobot", "--data", str(root), "--out", str(tmp_path / "back")]) == 0
    back = EpisodeStore(tmp_path / "back")
    assert back.views == src.views and back.fps == src.fps and len(back) == 2
    for a, b in zip(eps, (back.load(e) for e in back.episode_ids()), strict=True):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.ee_pose, b.ee_pose)
        assert a.prompt == b.prompt and b.meta["wrist_views"] == ["wrist"]
        for v in src.views:
            assert np.abs(a.frames[v].astype(float) - b.frames[v]).mean() < MAX_MAE, v
    # importing again skips what is there; a bad root is a clean error, not a traceback
    assert import_lerobot(root, tmp_path / "back")["skipped"] == 2
    assert main(["data", "import-lerobot", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2


def test_import_needs_a_7d_pose(datasets, tmp_path):
    root = datasets("v3.0")  # observation.state is 5-D here
    with pytest.raises(LeRobotError, match="7-D feature"):
        import_lerobot(root, tmp_path / "a")
    out = import_lerobot(root, tmp_path / "b", fps=10, image_size=(16, 24), allow_missing_pose=True)
    assert out["written"] == 3 and out["fps"] == 10
    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(tmp_path / "b")
    ep = store.load("lerobot000002")
    # no pose is written as none (not zeros that pseudo-actions would read as a robot standing still); the 5-D
    # observation.state is kept as the state, the 7-D actions read as the benchmark's delta_ee (no declaration)
    assert ep.length == 8 and ep.ee_pose is None and ep.prompt == TASKS[2] and not store.has_pose
    assert ep.frames["left"].shape == (8, 16, 24, 3) and ep.meta["ee_pose_source"] == "none"
    np.testing.assert_array_equal(ep.state, _episodes()[2].state[::2])
    assert store.state_dim == 5 and store.action_space.kind == "delta_ee"
    assert "labels" not in ep.meta and out["success_labels"] == 0  # no next.success column: no labels made up


def _labelled(lengths=LENGTHS, success_at=((11,), (), (3, 4))) -> list[RawEpisode]:
    """Episodes with LeRobot's one-value-per-frame features: next.success (bool [T, 1], true at ``success_at``) and
    a float gripper reading [T, 1]."""
    rng = np.random.default_rng(1)
    eps = []
    for e, n in enumerate(lengths):
        success = np.zeros((n, 1), bool)
        success[list(success_at[e]), 0] = True
        eps.append(RawEpisode({CAMS[0]: _smooth(n, e, size=16)}, rng.normal(size=(n, 7)).astype(np.float32),
                              TASKS[e], rng.normal(size=(n, 7)).astype(np.float32),
                              {"observation.gripper": rng.normal(size=(n, 1)).astype(np.float32),
                               "next.success": success}))
    return eps


@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_a_one_value_feature_is_written_as_lerobot_does_and_read_back(tmp_path, version):
    """A [T, 1] feature: "shape": [1] in info.json and a plain column in the parquet (LeRobot's datasets ``Value``;
    a list column under shape [1] is what LeRobot misreads), read back by our reader as the same values."""
    raw = _labelled()
    write_lerobot(tmp_path / "lr", raw, FPS, version=version, image_dtype="image")
    feats = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())["features"]
    assert (feats["observation.gripper"]["shape"], feats["observation.gripper"]["dtype"]) == ([1], "float32")
    assert (feats["next.success"]["shape"], feats["next.success"]["dtype"]) == ([1], "bool")
    schema = pq.read_schema(next((tmp_path / "lr" / "data").rglob("*.parquet")))
    assert schema.field("observation.gripper").type == pa.float32() and schema.field("next.success").type == pa.bool_()
    assert schema.field("action").type == pa.list_(pa.float32(), 7)  # vectors stay fixed-size lists
    hf = json.loads(schema.metadata[b"huggingface"])["info"]["features"]
    assert hf["observation.gripper"] == {"dtype": "float32", "_type": "Value"}
    src = LeRobotEpisodes(tmp_path / "lr", state_key="observation.gripper")
    for i, ep in enumerate(raw):
        got = src.episode(i)
        np.testing.assert_array_equal(got.state.reshape(-1, 1), ep.vectors["observation.gripper"])
        np.testing.assert_array_equal(got.actions, ep.action)
        assert got.success == bool(ep.vectors["next.success"].any())
    out = import_lerobot(tmp_path / "lr", tmp_path / "store", state_key="observation.gripper", pose_key=None,
                         allow_missing_pose=True)
    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(out["out"])
    assert store.state_dim == 1
    np.testing.assert_array_equal(store.load("lerobot000002").state, raw[2].vectors["observation.gripper"])


def test_import_keeps_next_success_as_the_real_outcome(tmp_path):
    """next.success becomes each episode's meta labels (any frame's, even one the import's fps skips), which
    `sc3 sweep episodes --real NAME=STORE` (evaluation/labels.py) reads with the LeRobot source gone."""
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.evaluation import labels

    write_lerobot(tmp_path / "lr", _labelled(), FPS, image_dtype="image")  # ep 0: success only on frame 11
    want = {0: True, 1: False, 2: True}
    assert labels.lerobot_success(tmp_path / "lr") == want  # what --real reads from the LeRobot dataset itself
    out = import_lerobot(tmp_path / "lr", tmp_path / "store", fps=10)  # keeps frames 0, 2, ..., 10 of episode 0
    assert out["success_labels"] == 3
    store = EpisodeStore(tmp_path / "store")
    metas = [store.load(e).meta for e in store.episode_ids()]
    assert [m["labels"] for m in metas] == [{"success": want[i]} for i in range(3)]
    shutil.rmtree(tmp_path / "lr")  # the store alone carries them now
    real = labels.read([f"pi={tmp_path / 'store'}"])
    assert [(r.policy, r.outcomes) for r in real] == [("pi", {"success": want[i]}) for i in range(3)]


def test_episodes_split_one_dataset_into_a_training_and_a_held_out_store(datasets, tmp_path, capsys):
    """`--episodes 0:1` and `--episodes 1:` import disjoint episodes of one dataset; the episode sweep counts the
    initial conditions its world model trained on (all of a training store's, none of the held-out one's)."""
    from sc3_jax.cli import main
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.evaluation.ic_sweep import trained_on

    root = datasets("v3.0")
    common = ["--image-size", "16", "24", "--allow-missing-pose"]
    assert main(["data", "import-lerobot", "--data", str(root), "--out", str(tmp_path / "train"), "--episodes", "0:1",
                 *common]) == 0
    assert main(["data", "import-lerobot", "--data", str(root), "--out", str(tmp_path / "held"), "--episodes", "1:",
                 *common]) == 0
    train, held = EpisodeStore(tmp_path / "train"), EpisodeStore(tmp_path / "held")
    assert train.episode_ids() == ["lerobot000000"] and held.episode_ids() == ["lerobot000001", "lerobot000002"]
    assert trained_on(held, held.episode_ids(), str(train.root)) == 0
    assert trained_on(train, train.episode_ids(), str(train.root)) == 1  # the same store
    written = import_lerobot(root, tmp_path / "both", image_size=(16, 24), allow_missing_pose=True, episodes={0, 2})
    both = EpisodeStore(tmp_path / "both")
    assert written["written"] == 2
    assert trained_on(both, both.episode_ids(), str(train.root)) == 1  # episode 0 of the same dataset
    assert trained_on(held, held.episode_ids(), str(tmp_path / "elsewhere")) is None  # not here to compare
    assert main(["data", "import-lerobot", "--data", str(root), "--out", str(tmp_path / "x"), "--episodes", "1-3"]) == 2
    assert "--episodes '1-3'" in capsys.readouterr().err
