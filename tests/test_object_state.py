"""The objects' state (LeRobot's observation.environment_state, e.g. a block's position): imported into the episode
store as ``object_state``, validated like the robot's state, exported back; stores without one (every store written
before it) read as before."""
import json

import numpy as np
import pytest

pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
pytest.importorskip("pyarrow", reason="LeRobot support needs the [lerobot] extra (pyarrow)")

from sc3_jax.data.episodes import Episode, EpisodeError, EpisodeStore  # noqa: E402
from sc3_jax.data.lerobot import ENVIRONMENT_STATE_KEY  # noqa: E402
from sc3_jax.data.lerobot_import import import_lerobot  # noqa: E402
from sc3_jax.data.lerobot_write import RawEpisode, export_store, write_lerobot  # noqa: E402

FPS = 10
LENGTHS = (9, 12)
OBJECTS = ["block_x", "block_y", "block_z", "goal_x", "goal_y", "goal_z"]
STATE = ["pan", "lift", "gripper"]


def _raw(with_objects: bool) -> list[RawEpisode]:
    """Two SO-101-like episodes: 4-D velocity actions (a gripper target among them), a 3-D state, one camera stored
    as PNGs (no video encode: fast) and, optionally, the block's and goal's positions."""
    rng = np.random.default_rng(0)
    eps = []
    for e, n in enumerate(LENGTHS):
        frames = {"observation.images.workspace": rng.integers(0, 255, (n, 8, 8, 3), dtype=np.uint8)}
        vectors = {ENVIRONMENT_STATE_KEY: rng.normal(size=(n, 6)).astype(np.float32)} if with_objects else {}
        eps.append(RawEpisode(frames, rng.normal(size=(n, 4)).astype(np.float32), "pick the block",
                              rng.normal(size=(n, 3)).astype(np.float32), vectors))
    return eps


def _write(root, with_objects: bool) -> list[RawEpisode]:
    raw = _raw(with_objects)
    names = {"action": ["dx", "dy", "dz", "gripper"], "observation.state": STATE, ENVIRONMENT_STATE_KEY: OBJECTS}
    write_lerobot(root, raw, FPS, image_dtype="image", names=names)
    return raw


def _import(src, out, **kw):
    return import_lerobot(src, out, action_space="velocity", action_targets=[3], **kw)


def _one_line(err) -> str:
    msg = str(err.value)
    assert msg and "\n" not in msg, msg
    return msg


def test_a_lerobot_dataset_with_an_environment_state_imports_it_and_one_without_imports_as_before(tmp_path):
    raw = _write(tmp_path / "with", True)
    summary = _import(tmp_path / "with", tmp_path / "store")
    store = EpisodeStore(tmp_path / "store")
    assert summary["object_state_dim"] == store.object_state_dim == 6 and store.object_state_names == tuple(OBJECTS)
    assert json.loads((tmp_path / "store" / "dataset.json").read_text())["object_state"] == {"dim": 6,
                                                                                             "names": OBJECTS}
    assert store.array_fields() == ("actions", "state", "object_state")
    for i, eid in enumerate(store.episode_ids()):
        ep = store.load(eid)
        assert ep.object_state.dtype == np.float32
        np.testing.assert_array_equal(ep.object_state, raw[i].vectors[ENVIRONMENT_STATE_KEY])
        np.testing.assert_array_equal(ep.state, raw[i].state)
        assert ep.meta["object_state_source"] == ENVIRONMENT_STATE_KEY

    _write(tmp_path / "without", False)
    summary = _import(tmp_path / "without", tmp_path / "plain")
    plain = EpisodeStore(tmp_path / "plain")
    assert summary["object_state_dim"] is None and plain.object_state_dim is None and plain.object_state_names == ()
    assert plain.array_fields() == ("actions", "state")
    assert json.loads((tmp_path / "plain" / "dataset.json").read_text())["object_state"] is None
    ep = plain.load(plain.episode_ids()[0])
    assert ep.object_state is None and "object_state_source" not in ep.meta
    assert sorted(p.name for p in (tmp_path / "plain" / ep.episode_id).iterdir()) == [
        "actions.npy", "frames", "meta.json", "state.npy"]  # the files of a store from before object states

    # object_state_key=None keeps it out of a dataset that has one
    assert _import(tmp_path / "with", tmp_path / "none", object_state_key=None)["object_state_dim"] is None


def test_an_exported_store_keeps_its_object_state_through_a_lerobot_round_trip(tmp_path):
    raw = _write(tmp_path / "lr", True)
    _import(tmp_path / "lr", tmp_path / "store")
    export_store(tmp_path / "store", tmp_path / "back_lr", image_dtype="image")
    feature = json.loads((tmp_path / "back_lr" / "meta" / "info.json").read_text())["features"][ENVIRONMENT_STATE_KEY]
    assert feature["shape"] == [6] and feature["names"] == OBJECTS
    back = EpisodeStore(import_lerobot(tmp_path / "back_lr", tmp_path / "back")["out"])
    assert back.object_state_names == tuple(OBJECTS)
    for i, eid in enumerate(back.episode_ids()):
        np.testing.assert_array_equal(back.load(eid).object_state, raw[i].vectors[ENVIRONMENT_STATE_KEY])


def test_a_resumed_import_into_a_store_written_without_object_states_keeps_its_declaration(tmp_path, capsys):
    """A store imported before object states were kept: importing into it again (resuming, or adding episodes)
    keeps it as it is -- no object state, said in one line -- instead of refusing the store as another dataset."""
    _write(tmp_path / "lr", True)
    _import(tmp_path / "lr", tmp_path / "store", object_state_key=None, episodes={0})
    out = _import(tmp_path / "lr", tmp_path / "store", progress=True)
    assert out["written"] == 1 and out["skipped"] == 1 and out["object_state_dim"] is None
    assert "written without object states" in capsys.readouterr().out
    assert EpisodeStore(tmp_path / "store").object_state_dim is None
    with pytest.raises(Exception) as e:  # asked for by name, it is the other dataset it would be
        _import(tmp_path / "lr", tmp_path / "store", object_state_key=ENVIRONMENT_STATE_KEY)
    assert "object_state" in _one_line(e)


def _store(root, object_dim: int | None = 2) -> EpisodeStore:
    return EpisodeStore(root, views=["cam"], fps=10, image_size=(4, 4), create=True, action_dim=7,
                        object_state_dim=object_dim, object_state_names=None if object_dim is None else ["x", "y"])


def _episode(n: int = 5, objects=None) -> Episode:
    return Episode("ep", {"cam": np.zeros((n, 4, 4, 3), np.uint8)}, np.zeros((n, 7), np.float32),
                   np.zeros((n, 7), np.float32), object_state=objects)


@pytest.mark.parametrize("objects, problem", [
    (None, "expected shape [5, 2]"),
    (np.zeros((4, 2)), "expected shape [5, 2]"),
    (np.zeros((5, 3)), "expected shape [5, 2]"),
    (np.array([[0, 0]] * 4 + [[np.nan, 0]]), "NaN/inf at steps [4]"),
])
def test_a_malformed_object_state_is_refused_naming_the_episode_and_field(tmp_path, objects, problem):
    store = _store(tmp_path / "s")
    with pytest.raises(EpisodeError) as e:
        store.write(_episode(objects=objects))
    assert e.value.field == "object_state" and problem in e.value.problem and _one_line(e)
    assert store.episode_ids() == []  # nothing written


def test_an_object_state_the_store_does_not_declare_is_refused(tmp_path):
    store = _store(tmp_path / "s", object_dim=None)
    with pytest.raises(EpisodeError) as e:
        store.write(_episode(objects=np.zeros((5, 2), np.float32)))
    assert e.value.field == "object_state" and "declares none" in e.value.problem


def test_a_store_written_before_object_states_reads_as_one_without(tmp_path):
    """dataset.json files from before have no "object_state" key: no object state, and reopening one to write more
    episodes (create=True with the same declarations) is not refused."""
    store = _store(tmp_path / "s", object_dim=None)
    store.write(_episode())
    header = tmp_path / "s" / "dataset.json"
    info = json.loads(header.read_text())
    del info["object_state"]
    header.write_text(json.dumps(info))
    old = EpisodeStore(tmp_path / "s")
    assert old.object_state_dim is None and old.array_fields() == ("actions", "ee_pose")
    assert old.load("ep").object_state is None
    _store(tmp_path / "s", object_dim=None)  # reopened with the same declarations
    info["object_state"] = {"dim": 2, "names": ["x"]}  # names that do not name every entry: one line
    header.write_text(json.dumps(info))
    with pytest.raises(Exception) as e:
        EpisodeStore(tmp_path / "s")
    assert "object_state" in _one_line(e)
