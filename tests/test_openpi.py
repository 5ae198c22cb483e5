"""openpi wire protocol: msgpack-numpy codec, observation mappings, our client <-> our server, openpi-client interop."""
from __future__ import annotations

import importlib
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import jax.numpy as jnp
import msgpack
import numpy as np
import pytest

from sc3_jax.core.errors import UserError
from sc3_jax.policies import msgpack_numpy as mn
from sc3_jax.policies.base import HostPolicy, JaxPolicy, as_host, check_dims
from sc3_jax.policies.openpi_client import (PolicyConnectionError, PolicyServerError, PolicyTimeoutError,
                                            WebsocketClientPolicy)
from sc3_jax.policies.openpi_mappings import (ALOHA, ALOHA_CAMERAS, DROID, LIBERO, ActionMap,
                                             get_mapping)
from sc3_jax.policies.openpi_server import PolicyServer, serve
from sc3_jax.benchmarks.bussing.tasks import PROMPTS  # a benchmark's task words, as --benchmark bussing sends them

CHUNK = 5


# ---------------------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------------------
def _apply(params, obs, rng):
    del rng
    img_mean = jnp.mean(obs["images"].astype(jnp.float32), axis=(1, 2, 3)) / 255.0  # [V]
    base = obs["state"].astype(jnp.float32) + jnp.sum(img_mean * params["view_w"]) + params["task_w"] * obs["task"]
    return base[None, :] + params["t"][:, None]  # [CHUNK, state dim]


def tiny_policy(dim=7, views=3) -> JaxPolicy:
    """Actions [CHUNK, dim] from a state [dim] and ``views`` views (dim 8: DROID, 14: ALOHA)."""
    params = {"view_w": jnp.arange(1.0, views + 1), "task_w": jnp.float32(0.5), "t": jnp.arange(CHUNK) * 0.01}
    return JaxPolicy("tiny", _apply, params, chunk=CHUNK, action_dim=dim)


def our_obs(h=48, w=64, task=1, seed=0, state_dim=7, views=3):
    """Constant-colour views (resizing / letterboxing / un-letterboxing them is exact)."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(0, 256, size=views)
    images = np.stack([np.full((h, w, 3), c, np.uint8) for c in colours])
    return {"images": images, "state": rng.normal(size=state_dim).astype(np.float32),
            "task": np.asarray(task, np.int32)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def assert_same(a, b, path="obj"):
    """Equal values *and* types/dtypes; arrays compared bitwise."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), path
        assert a.dtype == b.dtype and a.shape == b.shape, (path, a.dtype, b.dtype, a.shape, b.shape)
        assert a.tobytes() == b.tobytes(), path
    elif isinstance(a, np.generic):
        assert type(a) is type(b) and a.dtype == b.dtype, (path, type(a), type(b))
        assert a.tobytes() == b.tobytes(), path
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (path, set(a), set(b))
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    else:
        assert type(a) is type(b) and a == b, (path, a, b)


def payload(nan: bool = True):
    """Every kind of value the codec carries; ``nan``: one float32 NaN among them (the codec carries it exactly, a
    server refuses it: a policy would answer NaN actions)."""
    rng = np.random.default_rng(1)
    f32 = rng.normal(size=(4, 6)).astype(np.float32)
    f32[0, 0] = np.nan if nan else 0.5
    return {
        "images": rng.integers(0, 256, size=(3, 8, 10, 3), dtype=np.uint8),
        "f32_noncontig": f32[:, ::2],
        "big_endian": np.arange(6, dtype=">f8").reshape(2, 3),
        "f16": rng.normal(size=5).astype(np.float16),
        "bool": np.array([True, False, True]),
        "u64": np.array([0, 2**64 - 1], np.uint64),
        "zero_d": np.array(7, np.int16),
        "empty": np.zeros((0, 3), np.float32),
        "strs": np.array(["a", "bcd"]),
        "scalars": {"f32": np.float32(1.25), "f64": np.float64(-2.5), "i8": np.int8(-3), "u64": np.uint64(2**63 + 5),
                    "b": np.bool_(False), "s": np.str_("héllo"), "f16": np.float16(0.1)},
        "nested": {"a": {"b": [np.arange(3, dtype=np.int32), {"c": np.float32(3.0)}], "t": (1, 2.0, "x")}},
        "py": {"int": -5, "float": 0.5, "str": "prompt", "bytes": b"\x00\x01", "none": None, "bool": True},
    }


class EchoPolicy:
    """Returns a fixed action chunk and echoes the observation it received (a dict reply is passed through)."""
    chunk = 4

    def __init__(self):
        self.actions = np.random.default_rng(2).normal(size=(4, 7)).astype(np.float32)

    def infer(self, obs):
        return {"actions": self.actions, "echo": obs}


class FixedPolicy:
    chunk = 4

    def __init__(self):
        self.actions = np.random.default_rng(3).normal(size=(4, 7)).astype(np.float32)
        self.seen = []

    def infer(self, obs):
        self.seen.append(obs)
        return self.actions


class FailingPolicy:
    chunk = 4

    def infer(self, obs):
        raise ValueError("kaboom-4711")


class SlowPolicy:
    chunk = 4

    def infer(self, obs):
        time.sleep(1.0)
        return np.zeros((4, 7), np.float32)


@pytest.fixture
def server_factory():
    servers = []

    def make(policy, **kw):
        s = PolicyServer(policy, host="127.0.0.1", port=0, **kw).start()
        servers.append(s)
        return s

    yield make
    for s in servers:
        s.shutdown()


# ---------------------------------------------------------------------------------------------------------------------
# codec
# ---------------------------------------------------------------------------------------------------------------------
def test_msgpack_roundtrip_exact():
    p = payload()
    assert_same(p, mn.unpackb(mn.packb(p)))
    # the openpi encoding, byte for byte: bytes keys, dtype.str, shape
    raw = msgpack.unpackb(mn.packb(np.arange(3, dtype="<i4").reshape(1, 3)))
    assert raw == {b"__ndarray__": True, b"data": np.arange(3, dtype="<i4").tobytes(), b"dtype": "<i4",
                   b"shape": [1, 3]}
    assert msgpack.unpackb(mn.packb(np.float32(2.0))) == {b"__npgeneric__": True, b"data": 2.0, b"dtype": "<f4"}
    # decoded arrays are writable
    out = mn.unpackb(mn.packb(np.zeros(3)))
    out[0] = 1.0


@pytest.mark.parametrize("bad", [np.zeros(2, complex), np.array([object()], dtype=object),
                                 np.zeros(2, dtype=[("a", "f4")]), np.complex64(1j), np.zeros(1, "datetime64[s]")])
def test_msgpack_refuses_dtypes(bad):
    with pytest.raises(TypeError, match="refused"):
        mn.packb({"x": bad})


# ---------------------------------------------------------------------------------------------------------------------
# mappings
# ---------------------------------------------------------------------------------------------------------------------
def test_presets_keys_shapes_and_inverse():
    # Each preset now carries its robot's own state layout (DROID 8-D, LIBERO 7-D, ALOHA 14-D with 4 views), so each
    # gets an observation of that layout (this test used to feed all three our 7-D, 3-view benchmark observation).
    obs = our_obs(task=1, state_dim=8)
    s = obs["state"]
    assert "prompt" not in DROID.to_family(obs)  # a preset has no words of its own: the episodes' or a benchmark's
    droid = DROID.replace(prompts=PROMPTS).to_family(obs)
    assert set(droid) == {"observation/exterior_image_1_left", "observation/wrist_image_left",
                          "observation/joint_position", "observation/gripper_position", "prompt"}
    for k in ("observation/exterior_image_1_left", "observation/wrist_image_left"):
        assert droid[k].shape == (224, 224, 3) and droid[k].dtype == np.uint8
    # letterbox of a 48x64 frame: 168 rows of image, 28 black rows above and below
    ext = droid["observation/exterior_image_1_left"]
    assert (ext[:28] == 0).all() and (ext[-28:] == 0).all() and (ext[28:196] == obs["images"][0, 0, 0]).all()
    assert (droid["observation/wrist_image_left"][100, 100] == obs["images"][2, 0, 0]).all()  # wrist = last view
    np.testing.assert_array_equal(droid["observation/joint_position"], s[:7])
    np.testing.assert_array_equal(droid["observation/gripper_position"], s[7:8])
    assert droid["prompt"] == PROMPTS[1]

    lobs = our_obs(task=1)
    libero = LIBERO.replace(prompts=PROMPTS).to_family(lobs)
    assert set(libero) == {"observation/image", "observation/wrist_image", "observation/state", "prompt"}
    assert libero["observation/image"].shape == (224, 224, 3)
    ls = lobs["state"]
    np.testing.assert_array_equal(libero["observation/state"], np.r_[ls, -ls[6]].astype(np.float32))

    aobs = our_obs(task=1, state_dim=14, views=4)
    aloha = ALOHA.replace(prompts=PROMPTS).to_family(aobs)
    assert set(aloha) == {"images", "state", "prompt"}
    assert tuple(aloha["images"]) == ALOHA_CAMERAS
    for v in aloha["images"].values():
        assert v.shape == (3, 224, 224) and v.dtype == np.uint8
    np.testing.assert_array_equal(aloha["state"], aobs["state"])

    # inverse (server side): back to our observation; constant views survive exactly
    for m, o, fobs in ((DROID, obs, droid), (LIBERO, lobs, libero), (ALOHA, aobs, aloha)):
        back = m.replace(our_image_size=(48, 64), prompts=PROMPTS).from_family(fobs)
        n = m.num_views
        assert back["images"].shape == (n, 48, 64, 3) and back["images"].dtype == np.uint8
        np.testing.assert_array_equal(back["state"], o["state"])
        assert back["task"].dtype == np.int32 and int(back["task"]) == 1
        sent = {m._view_index(vf.view, n) for vf in m.views}
        for v in range(n):
            np.testing.assert_array_equal(back["images"][v], o["images"][v] if v in sent else 0)
    assert DROID.from_family(droid)["images"].shape == (3, 224, 224, 3)  # our_image_size=None keeps the family size

    # prompts: fixed prompt, unknown prompt
    assert DROID.replace(prompts="do it").to_family(obs)["prompt"] == "do it"
    with pytest.raises(ValueError, match="matches no task"):
        DROID.replace(prompts=PROMPTS).from_family({**droid, "prompt": "dance"})
    assert int(DROID.replace(default_task=0).from_family({**droid, "prompt": "dance"})["task"]) == 0
    assert get_mapping("native") is None and get_mapping("DROID") is DROID


def test_action_mapping():
    # DROID is now the identity over openpi's 8 dims (7 joint velocities + gripper) for an 8-D model; it used to
    # squeeze them into our 7-D delta-EE layout by dropping dim 6.
    fam = np.random.default_rng(0).normal(size=(10, 8)).astype(np.float32)
    # DROID refuses a reply shorter than the chunk (holding a joint velocity keeps the arm moving); "hold" on request
    with pytest.raises(UserError, match="returned 10 actions but a chunk of 12 is needed"):
        DROID.actions_to_ours(fam, 12)
    hold = DROID.replace(pad_actions="hold")
    ours = hold.actions_to_ours(fam, chunk=12)
    assert ours.shape == (12, 8) and ours.dtype == np.float32
    np.testing.assert_array_equal(ours[:10], fam)
    np.testing.assert_array_equal(ours[10:], np.repeat(fam[-1:], 2, 0))  # "hold"
    np.testing.assert_array_equal(DROID.actions_to_ours(fam, chunk=4), ours[:4])
    assert (DROID.replace(pad_actions="zeros").actions_to_ours(fam, 12)[10:] == 0).all()
    back = DROID.actions_to_family(ours)
    assert back.shape == (12, 8)
    np.testing.assert_array_equal(DROID.actions_to_ours(back, 12), ours)
    # a mapping that reads a subset still scatters back with zeros in the family dims we do not produce
    sub = hold.replace(action_map=ActionMap(family_dim=8, indices=(0, 1, 2, 3, 4, 5, 7)))
    ours7 = sub.actions_to_ours(fam, 10)
    np.testing.assert_array_equal(ours7, fam[:, [0, 1, 2, 3, 4, 5, 7]])
    back7 = sub.actions_to_family(ours7)
    assert (back7[:, 6] == 0).all() and (back7[:, [0, 1, 2, 3, 4, 5, 7]] == ours7).all()
    assert ALOHA.actions_to_family(np.zeros((12, 14), np.float32)).shape == (12, 14)


def test_aloha_roundtrip_14d_four_views(server_factory):
    """openpi ALOHA: both arms, [left 6 joints, left gripper, right 6 joints, right gripper], 4 CHW cameras."""
    obs = our_obs(task=0, state_dim=14, views=4)
    fam = ALOHA.to_family(obs)
    assert tuple(fam["images"]) == ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
    for cam, img in zip(ALOHA_CAMERAS, obs["images"]):
        assert fam["images"][cam].shape == (3, 224, 224) and fam["images"][cam].dtype == np.uint8
        assert (fam["images"][cam][:, 112, 112] == img[0, 0]).all()  # view i -> camera i, CHW
    assert fam["state"].shape == (14,) and fam["state"].dtype == np.float32
    np.testing.assert_array_equal(fam["state"], obs["state"])  # right arm included, not zero padding
    # ours -> family -> ours is the identity: images (constant colours survive the letterbox), state, task, actions
    m = ALOHA.replace(our_image_size=(48, 64))
    back = m.from_family(fam)
    assert_same(obs, back)
    chunk = np.random.default_rng(4).normal(size=(CHUNK, 14)).astype(np.float32)
    fam_actions = ALOHA.actions_to_family(chunk)
    assert fam_actions.shape == (CHUNK, 14)
    np.testing.assert_array_equal(fam_actions, chunk)
    np.testing.assert_array_equal(ALOHA.actions_to_ours(fam_actions, CHUNK), chunk)
    # and over the wire: a 14-D, 4-view policy served as ALOHA, queried by our ALOHA client
    policy = tiny_policy(14, views=4)
    server = server_factory(policy, mapping=m)
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping=m, action_dim=14) as client:
        assert client.metadata["family"] == "aloha" and client.metadata["action_dim"] == 14
        got = client.infer(obs)
    assert got.shape == (CHUNK, 14)
    np.testing.assert_allclose(got, as_host(policy).infer(obs), rtol=0, atol=1e-6)


def test_droid_shapes_and_names():
    """openpi DROID: HWC 224x224 exterior + wrist images, joint_position [7] + gripper_position [1], actions [H, 8]."""
    obs = our_obs(h=180, w=320, state_dim=8)
    fam = DROID.to_family(obs)
    assert {k: (v.shape, v.dtype) for k, v in fam.items() if k != "prompt"} == {
        "observation/exterior_image_1_left": ((224, 224, 3), np.uint8),
        "observation/wrist_image_left": ((224, 224, 3), np.uint8),
        "observation/joint_position": ((7,), np.float32),
        "observation/gripper_position": ((1,), np.float32)}
    top = (224 - int(180 / (320 / 224))) // 2  # resize_with_pad: 320x180 -> 224x126, 49 black rows above
    assert (fam["observation/exterior_image_1_left"][:top] == 0).all()
    assert (fam["observation/exterior_image_1_left"][top + 1] == obs["images"][0, 0, 0]).all()
    assert (fam["observation/wrist_image_left"][112, 112] == obs["images"][-1, 0, 0]).all()
    assert DROID.action_dim == 8 and DROID.our_state_dim == 8 and DROID.action_map.family_dim == 8
    chunk = np.arange(CHUNK * 8, dtype=np.float32).reshape(CHUNK, 8)
    np.testing.assert_array_equal(DROID.actions_to_ours(DROID.actions_to_family(chunk), CHUNK), chunk)
    # openpi's DroidInputs also accepts a 0-d gripper position
    back = DROID.from_family({**fam, "observation/gripper_position": np.float32(0.25)})
    assert back["state"].shape == (8,) and back["state"][7] == 0.25


# ---------------------------------------------------------------------------------------------------------------------
# fake openpi servers: each answers in its family's layout (openpi@15a9616 *_policy.py, training/config.py) and records
# the raw request, so the tests see exactly what crossed the wire
# ---------------------------------------------------------------------------------------------------------------------
def _rowcol(h, d):
    """actions[t, j] = 100 t + j: any slicing, reordering or padding of rows or dims shows."""
    return (100 * np.arange(h)[:, None] + np.arange(d)[None, :]).astype(np.float32)


class FakeOpenpiDroid:
    """pi0_droid: DroidInputs' reads (joint_position ++ gripper_position, exterior 1 + wrist, HWC), then
    DroidOutputs' [..., :8] of the model's 32 dims, action_horizon 10. No ``chunk`` attribute: openpi's DROID
    server sends no chunk in its metadata."""

    def __init__(self, horizon=10):
        self.horizon, self.seen = horizon, []

    def infer(self, obs):
        self.seen.append(obs)
        gripper = np.asarray(obs["observation/gripper_position"])
        state = np.concatenate([obs["observation/joint_position"], gripper[None] if gripper.ndim == 0 else gripper])
        assert state.shape == (8,)
        for k in ("observation/exterior_image_1_left", "observation/wrist_image_left"):
            assert obs[k].shape[-1] == 3  # DroidInputs' _parse_image would transpose a CHW image
        return {"actions": _rowcol(self.horizon, 32)[:, :8], "policy_timing": {"infer_ms": 1.0}}


class FakeOpenpiAloha:
    """pi0_aloha: AlohaInputs' reads (cameras within EXPECTED_CAMERAS, CHW -> HWC, state [14]), then AlohaOutputs'
    [:, :14] of the model's 32 dims, action_horizon 50."""

    def __init__(self):
        self.seen = []

    def infer(self, obs):
        self.seen.append(obs)
        assert not set(obs["images"]) - set(ALOHA_CAMERAS)
        hwc = {k: np.transpose(v, (1, 2, 0)) for k, v in obs["images"].items()}  # einops "c h w -> h w c"
        assert all(v.shape == (224, 224, 3) for v in hwc.values())
        assert np.asarray(obs["state"]).shape == (14,)
        return {"actions": _rowcol(50, 32)[:, :14], "policy_timing": {"infer_ms": 1.0}}


def test_droid_against_fake_openpi_server(server_factory):
    fake = FakeOpenpiDroid()
    server = server_factory(fake)  # native: the fake gets the raw family dict and its reply goes back as is
    obs = our_obs(h=180, w=320, task=0, state_dim=8)  # a ZED-like 16:9 frame; views: exterior 1, exterior 2, wrist
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping=DROID.replace(prompts=PROMPTS), action_dim=8,
                               state_dim=8, views=3) as client:
        assert client.chunk == 8  # examples/droid/main.py's open_loop_horizon (the server's metadata has no chunk)
        got = client.infer(obs)
    sent = fake.seen[-1]
    assert {k: (v.shape, v.dtype) if isinstance(v, np.ndarray) else v for k, v in sent.items()} == {
        "observation/exterior_image_1_left": ((224, 224, 3), np.uint8),
        "observation/wrist_image_left": ((224, 224, 3), np.uint8),
        "observation/joint_position": ((7,), np.float32),
        "observation/gripper_position": ((1,), np.float32),
        "prompt": PROMPTS[0]}
    top = (224 - int(180 / (320 / 224))) // 2  # the client letterboxes: 320x180 -> 224x126, 49 black rows above
    ext, wrist = sent["observation/exterior_image_1_left"], sent["observation/wrist_image_left"]
    assert (ext[:top] == 0).all() and (ext[top + 1:top + 125] == obs["images"][0, 0, 0]).all()
    assert (wrist[112, 112] == obs["images"][2, 0, 0]).all()  # the wrist is our last view, not exterior 2
    np.testing.assert_array_equal(sent["observation/joint_position"], obs["state"][:7])
    np.testing.assert_array_equal(sent["observation/gripper_position"], obs["state"][7:])
    # the first 8 of the 10 rows, all 8 dims in order: 7 joint velocities + gripper position
    assert got.shape == (8, 8) and got.dtype == np.float32
    np.testing.assert_array_equal(got, _rowcol(8, 8))
    # a reply shorter than the chunk asked for is refused, not padded with a held joint velocity
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping="droid", chunk=12) as client:
        with pytest.raises(UserError, match="returned 10 actions but a chunk of 12 is needed"):
            client.infer(obs)


def test_aloha_against_fake_openpi_server(server_factory):
    fake = FakeOpenpiAloha()
    server = server_factory(fake, metadata={"reset_pose": [0, -1.5, 1.5, 0, 0, 0]})  # pi0_aloha's policy_metadata
    obs = our_obs(h=480, w=640, task=1, state_dim=14, views=4)  # real_env.py's 480x640 cameras
    obs["state"] = np.arange(14, dtype=np.float32) + 1  # [left 6 joints, left gripper, right 6 joints, right gripper]
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping=ALOHA.replace(prompts=PROMPTS), action_dim=14,
                               state_dim=14, views=4) as client:
        assert client.chunk == 25  # examples/aloha_real/main.py's action_horizon
        assert client.metadata["reset_pose"] == [0, -1.5, 1.5, 0, 0, 0]
        got = client.infer(obs)
    sent = fake.seen[-1]
    assert set(sent) == {"images", "state", "prompt"} and sent["prompt"] == PROMPTS[1]
    assert list(sent["images"]) == list(ALOHA_CAMERAS)
    for i, cam in enumerate(ALOHA_CAMERAS):  # view i -> camera i, CHW uint8, letterboxed 640x480 -> 224x168
        img = sent["images"][cam]
        assert img.shape == (3, 224, 224) and img.dtype == np.uint8
        assert (img[:, :28] == 0).all() and (img[:, 196:] == 0).all()
        assert (img[:, 28:196] == obs["images"][i, 0, 0][:, None, None]).all()
    assert sent["state"].dtype == np.float32
    np.testing.assert_array_equal(sent["state"], obs["state"])  # both arms, raw: adapt_to_pi is the server's
    # the first 25 of the 50 rows, all 14 dims in order: both arms
    assert got.shape == (25, 14) and got.dtype == np.float32
    np.testing.assert_array_equal(got, _rowcol(25, 14))
    # without a prompt, like examples/aloha_real/env.py (the server's default_prompt applies)
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping=ALOHA.replace(prompts=None)) as client:
        client.infer(obs)
    assert set(fake.seen[-1]) == {"images", "state"}


def test_dimension_mismatch_is_one_line_user_error(server_factory):
    """A 7-D model, or 3 views, with the 14-D, 4-camera ALOHA preset must not silently drive one arm: every entry
    point refuses with a one-line UserError naming both sides, the client before it connects."""
    msg = r"'aloha' carries 14-D actions but .* has 7-D actions"

    def refused(fn, match):
        with pytest.raises(UserError, match=match) as ei:
            fn()
        assert "\n" not in str(ei.value)

    refused(lambda: ALOHA.check_dims(action_dim=7), msg)
    refused(lambda: ALOHA.actions_to_family(np.zeros((CHUNK, 7), np.float32)), msg)
    refused(lambda: ALOHA.to_family(our_obs(state_dim=7, views=4)),
            r"'aloha' carries 14-D states but the observation has 7-D states")
    views_msg = (r"'aloha' sends 4 cameras \(cam_high, cam_low, cam_left_wrist, cam_right_wrist\) read from 4 views "
                 r"but {} has 3 views")
    refused(lambda: ALOHA.to_family(our_obs(state_dim=14, views=3)), views_msg.format("the observation"))
    refused(lambda: ALOHA.check_dims(views=3, who="the world model"), views_msg.format("the world model"))
    refused(lambda: ALOHA.replace(num_views=3), r"read from 4 views but num_views is 3")  # serve-policy --num-views 3
    # DROID reads view 0 and the last view: one view would send the same camera twice
    refused(lambda: DROID.to_family(our_obs(state_dim=8, views=1)), r"'droid' sends 2 cameras .* but the observation "
            r"has 1 views")
    assert (DROID.min_views, LIBERO.min_views, ALOHA.min_views) == (2, 2, 4)
    refused(lambda: PolicyServer(tiny_policy(7), host="127.0.0.1", port=0, mapping="droid"),
            r"'droid' carries 8-D actions but policy 'tiny' has 7-D actions")
    # refused before any connection is attempted (port 1 is closed: a connection attempt would raise another error)
    refused(lambda: WebsocketClientPolicy("127.0.0.1", 1, mapping="aloha", action_dim=7, max_retries=0), msg)
    refused(lambda: WebsocketClientPolicy("127.0.0.1", 1, mapping="aloha", views=3, max_retries=0),
            views_msg.format("the model"))
    refused(lambda: WebsocketClientPolicy("127.0.0.1", 1, mapping="droid", state_dim=7, max_retries=0),
            r"'droid' carries 8-D states but the model has 7-D states")
    # the server side: a client sending one arm's state is refused, not zero-filled
    fam = ALOHA.to_family(our_obs(state_dim=14, views=4))
    refused(lambda: ALOHA.from_family({**fam, "state": fam["state"][:7]}),
            r"sent 'state' with 7 entries but openpi mapping 'aloha' reads 14")
    # a HostPolicy that does not declare its dimension is caught at its first reply (the client sees its one line)
    server = server_factory(FixedPolicy(), mapping=ALOHA.replace(our_image_size=(48, 64)))
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping="aloha", max_retries=0) as client:
        # what a world model's check (rollout.check_policy -> base.check_dims) reads off the client, before compiling
        # chunk 4: the server's metadata wins over the preset's 25
        assert (client.action_dim, client.state_dim, client.min_views, client.chunk) == (14, 14, 4, 4)
        with pytest.raises(UserError, match=r"policy 'served' has 14-D actions \(action_dim\), the world model has "
                                            r"7-D actions"):
            check_dims(client, 7, 7, "served")
        with pytest.raises(PolicyServerError, match="carries 14-D actions but the policy's action chunk has 7-D"):
            client.infer(our_obs(state_dim=14, views=4))


# ---------------------------------------------------------------------------------------------------------------------
# client <-> server
# ---------------------------------------------------------------------------------------------------------------------
def test_roundtrip_exact_native(server_factory):
    echo = EchoPolicy()
    server = server_factory(echo, metadata={"extra": np.arange(2)})
    with WebsocketClientPolicy("127.0.0.1", server.port, timeout_s=10) as client:
        assert client.metadata["policy"] == "EchoPolicy" and client.metadata["chunk"] == 4
        assert_same(client.metadata["extra"], np.arange(2))
        p = payload(nan=False)
        reply = client.infer_raw(p)
        assert_same(p, reply["echo"])
        assert_same(echo.actions, reply["actions"])
        assert set(reply["server_timing"]) == {"infer_ms"}
        assert "prev_total_ms" in client.infer_raw(p)["server_timing"]  # the same arrays: a new shape is refused
        with pytest.raises(PolicyServerError, match="observation f32_noncontig holds NaN or inf"):
            client.infer_raw(payload(nan=True))

    fixed = FixedPolicy()
    server = server_factory(fixed)
    obs = our_obs()
    with WebsocketClientPolicy(f"ws://127.0.0.1:{server.port}", None) as client:
        acts = client.infer(obs)
        assert client.chunk == 4
        assert_same(fixed.actions, acts)
        assert_same(obs, fixed.seen[-1])


def test_jax_policy_served_native_and_droid(server_factory):
    policy = tiny_policy()
    local = as_host(policy)
    obs = our_obs(task=1)
    server = server_factory(policy)
    with WebsocketClientPolicy("127.0.0.1", server.port) as client:
        assert isinstance(client, HostPolicy)
        assert client.chunk == CHUNK and client.metadata["policy"] == "tiny"
        np.testing.assert_array_equal(client.infer(obs), local.infer(obs))

    # DROID carries an 8-D robot (7 joints + gripper): an 8-D policy and state (this used to be our 7-D policy)
    policy = tiny_policy(8)
    local = as_host(policy)
    obs = our_obs(task=1, state_dim=8)
    mapping = DROID.replace(our_image_size=(48, 64), pad_actions="hold", prompts=PROMPTS)  # task 1 rides its prompt
    server = server_factory(policy, mapping=mapping)
    with WebsocketClientPolicy("127.0.0.1", server.port, mapping=mapping, chunk=8) as client:
        assert client.metadata["family"] == "droid" and client.metadata["action_dim"] == 8
        got = client.infer(obs)
        # DROID sends views 0 and -1; the server's view 1 is black
        expected_obs = {**obs, "images": obs["images"] * np.array([1, 0, 1], np.uint8)[:, None, None, None]}
        expected = local.infer(expected_obs)
        assert got.shape == (8, 8)
        np.testing.assert_allclose(got[:CHUNK], expected, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(got[CHUNK:], np.repeat(got[CHUNK - 1:CHUNK], 8 - CHUNK, 0))


def test_server_error_text_frame(server_factory):
    server = server_factory(FailingPolicy())
    client = WebsocketClientPolicy("127.0.0.1", server.port, max_retries=1, backoff_s=0.01)
    with pytest.raises(PolicyServerError) as ei:
        client.infer(our_obs())
    msg = str(ei.value)
    # one line naming the error, no traceback and no server path (those stay in the server's log)
    assert "kaboom-4711" in msg and "Traceback" not in msg and f"127.0.0.1:{server.port}" in msg
    with pytest.raises(PolicyServerError, match="kaboom-4711"):  # the client reconnects; the error is reported again
        client.infer(our_obs())
    client.close()


def test_dead_port_bounded_retries():
    port = free_port()
    t0 = time.monotonic()
    with pytest.raises(PolicyConnectionError) as ei:
        WebsocketClientPolicy("127.0.0.1", port, max_retries=3, backoff_s=0.05, timeout_s=2)
    elapsed = time.monotonic() - t0
    assert f"127.0.0.1:{port}" in str(ei.value) and "4 attempts" in str(ei.value)
    assert 0.3 <= elapsed < 3.0  # 0.05 + 0.1 + 0.2 s of back-off


def test_reconnects_after_server_restart(server_factory):
    first = server_factory(FixedPolicy())
    port = first.port
    client = WebsocketClientPolicy("127.0.0.1", port, max_retries=6, backoff_s=0.05)
    a = client.infer(our_obs())
    first.shutdown()
    # the server comes back on the same port a little later; the client's back-off loop finds it
    later = {}
    t = threading.Timer(0.3, lambda: later.setdefault("s", PolicyServer(FixedPolicy(), "127.0.0.1", port).start()))
    t.start()
    try:
        np.testing.assert_array_equal(client.infer(our_obs()), a)
    finally:
        t.join()
        client.close()
        later["s"].shutdown()


def test_timeout(server_factory):
    server = server_factory(SlowPolicy())
    client = WebsocketClientPolicy("127.0.0.1", server.port, timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(PolicyTimeoutError, match="did not answer within 0.2s"):
        client.infer(our_obs())
    assert time.monotonic() - t0 < 0.9
    client.close()


def test_healthz_and_api_key(server_factory):
    server = server_factory(FixedPolicy(), api_key="s3cret")
    with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=5) as r:
        assert r.status == 200 and r.read().splitlines()[0] == b"OK"  # then what it expects and serves
    with pytest.raises(PolicyConnectionError, match="401"):
        WebsocketClientPolicy("127.0.0.1", server.port, max_retries=5, backoff_s=5)  # not retried: fails at once
    with WebsocketClientPolicy("127.0.0.1", server.port, api_key="s3cret") as client:
        assert client.infer(our_obs()).shape == (4, 7)


def test_serve_nonblocking_and_shutdown_idempotent():
    server = serve(FixedPolicy(), host="127.0.0.1", port=0, block=False)
    assert server.port > 0
    with WebsocketClientPolicy("127.0.0.1", server.port) as client:
        client.infer(our_obs())
    server.shutdown()
    server.shutdown()
    PolicyServer(FixedPolicy(), host="127.0.0.1", port=0).shutdown()  # never started: closes the socket at once


def test_serve_policy_cli_builds_server():
    from sc3_jax.commands import parse, serve_policy

    server = serve_policy.build_server(parse(serve_policy.Args, [
        "--policy", f"{__name__}:tiny_policy", "--host", "127.0.0.1", "--port", "0", "--family", "libero",
        "--image-size", "48", "64", "--task-prompt", "3=wipe it", "--log-level", "WARNING"], "serve-policy")).start()
    try:
        assert server.mapping.name == "libero" and server.mapping.our_image_size == (48, 64)
        assert server.metadata["policy"] == "tiny" and server.metadata["family"] == "libero"
        obs = our_obs(task=3)
        with WebsocketClientPolicy("127.0.0.1", server.port, mapping=server.mapping) as client:
            got = client.infer(obs)
        expected_obs = {**obs, "images": obs["images"] * np.array([1, 0, 1], np.uint8)[:, None, None, None]}
        np.testing.assert_allclose(got, as_host(tiny_policy()).infer(expected_obs), rtol=0, atol=1e-6)
    finally:
        server.shutdown()


# ---------------------------------------------------------------------------------------------------------------------
# the real openpi-client (optional: installed with --no-deps into a temporary directory)
# ---------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def openpi_client(tmp_path_factory):
    target = tmp_path_factory.mktemp("openpi_client")
    try:
        r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                            "--no-deps", "--target", str(target), "openpi-client"],
                           capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as e:
        pytest.skip(f"could not run pip to install openpi-client: {e}")
    if r.returncode != 0:
        pytest.skip(f"pip install --no-deps openpi-client failed (no network?): {r.stderr.strip()[-300:]}")
    sys.path.insert(0, str(target))
    try:
        wcp = importlib.import_module("openpi_client.websocket_client_policy")
        omn = importlib.import_module("openpi_client.msgpack_numpy")
    except ImportError as e:
        pytest.skip(f"openpi-client installed but not importable without its dependencies: {e}")
    finally:
        sys.path.remove(str(target))
    return wcp, omn


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # openpi-client's own connect() call on websockets >= 17
def test_real_openpi_client(openpi_client, server_factory):
    wcp, omn = openpi_client
    # codecs agree both ways (openpi's packer turns np.float64 scalars into floats, so use arrays and float32 scalars)
    p = {k: v for k, v in payload().items() if k not in ("scalars", "py")}
    p["s"] = np.float32(1.5)
    assert_same(p, omn.unpackb(mn.packb(p)))
    assert_same(p, mn.unpackb(omn.packb(p)))

    policy = tiny_policy(8)  # DROID: an 8-D robot
    mapping = DROID.replace(our_image_size=(48, 64))
    server = server_factory(policy, mapping=mapping, metadata={"note": "sc3"})
    client = wcp.WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    assert client.get_server_metadata()["note"] == "sc3"
    fobs = mapping.to_family(our_obs(task=0, state_dim=8))
    reply = client.infer(fobs)
    expected = mapping.actions_to_family(as_host(policy).infer(mapping.from_family(fobs)))
    assert reply["actions"].shape == (CHUNK, 8) and reply["actions"].dtype == np.float32
    np.testing.assert_array_equal(reply["actions"], expected)
    assert "infer_ms" in reply["server_timing"]
    client._ws.close()
