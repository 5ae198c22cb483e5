"""openpi's policy-server WebSocket protocol: a client (evaluate any openpi policy) and a server (serve ours).

Wire protocol (openpi ``serve_policy.py`` / ``openpi_client``), see docs/openpi.md:
  * ``ws://host:port`` (default port 8000), no compression, no message size limit, optional
    ``Authorization: Api-Key <key>`` header; ``GET /healthz`` answers 200 ``OK``.
  * on connect the server sends one binary frame: msgpack(metadata dict) (may be ``{}``);
  * each request is a binary msgpack(observation dict); the reply a binary msgpack(result dict) holding
    ``"actions"`` float [H, D] (plus ``"server_timing"`` / ``"policy_timing"``);
  * a *text* frame is a server-side traceback, after which the server closes the connection.
Arrays travel in openpi's msgpack-numpy encoding (:mod:`sc3_jax.policies.msgpack_numpy`).

Observation keys differ per openpi policy family; :class:`ObsMapping` translates between our observation
(``{"images": uint8 [V,H,W,3], "state": float32 [7], "task": int32 []}``, see ``base.py``) and a family's keys, and
between our action chunk (float32 [chunk, 7] delta end-effector) and the family's ``"actions"`` [H, D]. Presets:
:data:`DROID`, :data:`LIBERO`, :data:`ALOHA`. ``mapping=None`` ("native") sends our observation dict unchanged.

Semantics caveat (documented, not hidden): our 7-D state is an end-effector pose (x, y, z, rotvec, gripper) and our
actions are delta end-effector actions. DROID policies expect joint positions and emit joint velocities, ALOHA
policies expect/emit bimanual joint positions; the DROID/ALOHA presets route our numbers into those slots so that the
protocol works end to end, but a meaningful evaluation needs a policy trained on (or a mapping to) our action space.
LIBERO's state/action convention (EE pose + gripper, delta EE actions) is the closest to ours.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import logging
import threading
import time
import traceback
from http import HTTPStatus
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import websockets
import websockets.exceptions
import websockets.sync.client
import websockets.sync.server
from websockets.frames import CloseCode

from sc3_jax.policies import msgpack_numpy
from sc3_jax.policies.base import HostPolicy, JaxPolicy, as_host

__all__ = [
    "ViewField", "StateField", "ActionMap", "ObsMapping", "DROID", "LIBERO", "ALOHA", "PRESETS", "DEFAULT_PROMPTS",
    "get_mapping", "resize_with_pad", "PolicyServerError", "PolicyConnectionError", "PolicyTimeoutError",
    "WebsocketClientPolicy", "PolicyServer", "serve", "serve_policy_main", "build_policy_server", "DEFAULT_CHUNK",
]

logger = logging.getLogger(__name__)

DEFAULT_CHUNK = 25  # paper: policy chunk 25
DEFAULT_PROMPTS: dict[int, str] = {
    0: "put the utensils in the bin and the trash in the trash can",  # bussing (in-distribution)
    1: "put the utensils in the trash can and the trash in the bin",  # reverse bussing (out-of-distribution)
}

KeyPath = str | tuple[str, ...]  # a tuple addresses a nested dict, e.g. ("images", "cam_high")


# ----------------------------------------------------------------------------------------------------------------------
# Observation / action mapping
# ----------------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ViewField:
    """One family image key <- one of our views: an index into ``images`` (negative counts from the end, so -1 is
    the wrist view, which is last in dataset order) or a name from ``ObsMapping.view_names``."""
    key: KeyPath
    view: int | str


@dataclasses.dataclass(frozen=True)
class StateField:
    """One family state key <- ``state[indices] * scale``, zero-padded at the end to ``pad_to`` entries."""
    key: KeyPath
    indices: tuple[int, ...]
    scale: tuple[float, ...] | None = None
    pad_to: int | None = None


@dataclasses.dataclass(frozen=True)
class ActionMap:
    """Our action dim ``i`` = family ``actions[:, indices[i]] * scale[i]``; ``family_dim`` is D of the family's
    ``"actions"`` [H, D] (used when serving: family dims we do not produce are zero)."""
    family_dim: int
    indices: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6)
    scale: tuple[float, ...] | None = None


def _get(d: Mapping, key: KeyPath) -> Any:
    for k in (key,) if isinstance(key, str) else key:
        d = d[k]
    return d


def _has(d: Mapping, key: KeyPath) -> bool:
    try:
        _get(d, key)
        return True
    except (KeyError, TypeError):
        return False


def _put(d: dict, key: KeyPath, value: Any) -> None:
    path = (key,) if isinstance(key, str) else tuple(key)
    for k in path[:-1]:
        d = d.setdefault(k, {})
    d[path[-1]] = value


def _to_uint8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    if np.issubdtype(img.dtype, np.floating):
        scale = 255.0 if img.size and float(np.nanmax(img)) <= 1.0 else 1.0
        return np.clip(np.rint(img * scale), 0, 255).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


def _cv2_resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    import cv2

    if img.shape[:2] == (h, w):
        return img
    shrink = h < img.shape[0] or w < img.shape[1]
    out = cv2.resize(np.ascontiguousarray(img), (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return out.reshape(h, w, *img.shape[2:])  # cv2 drops a trailing channel axis of size 1


def _pad_box(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> tuple[int, int, int, int]:
    """(top, left, height, width) of a src-sized image letterboxed into dst (openpi ``resize_with_pad`` geometry)."""
    (sh, sw), (h, w) = src_hw, dst_hw
    ratio = max(sw / w, sh / h)
    rh, rw = int(sh / ratio), int(sw / ratio)
    return max(0, (h - rh) // 2), max(0, (w - rw) // 2), rh, rw


def resize_with_pad(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Resize HWC ``img`` to fit ``h x w`` keeping its aspect ratio and zero-pad the rest (centred), the geometry of
    openpi's ``image_tools.resize_with_pad`` (which uses PIL bilinear; here cv2, INTER_AREA when shrinking)."""
    if img.shape[:2] == (h, w):
        return img
    top, left, rh, rw = _pad_box(img.shape[:2], (h, w))
    out = np.zeros((h, w, *img.shape[2:]), img.dtype)
    out[top:top + rh, left:left + rw] = _cv2_resize(img, rh, rw)
    return out


def _fit_rows(actions: np.ndarray, chunk: int, pad: str, where: str) -> np.ndarray:
    """Slice [H, D] to [chunk, D], or pad when H < chunk: "hold" repeats the last action, "zeros" appends zeros,
    "error" raises."""
    h = actions.shape[0]
    if h >= chunk:
        return actions[:chunk]
    if pad == "error" or h == 0:
        raise ValueError(f"{where} returned {h} actions but a chunk of {chunk} is needed (pad_actions={pad!r})")
    if pad == "hold":
        fill = np.repeat(actions[-1:], chunk - h, axis=0)
    elif pad == "zeros":
        fill = np.zeros((chunk - h, *actions.shape[1:]), actions.dtype)
    else:
        raise ValueError(f"unknown pad_actions {pad!r} (expected 'hold', 'zeros' or 'error')")
    return np.concatenate([actions, fill], axis=0)


@dataclasses.dataclass(frozen=True)
class ObsMapping:
    """Our observation <-> an openpi policy family's observation, and our action chunk <-> the family's actions.

    Client side (``to_family``): each :class:`ViewField` picks one of our views, resizes it to ``image_size``
    (``resize="pad"``: openpi's keep-aspect letterbox; ``"stretch"``: plain resize; ``image_size=None``: as is) and
    transposes it to CHW when ``channels_first``; each :class:`StateField` slices/scales/pads ``state``; the prompt is
    ``prompts[task]`` (a task-id -> prompt table) or ``prompts`` itself when it is a string (fixed prompt; None: no
    prompt key). ``extra`` entries are sent unchanged with every request.
    ``actions_to_ours`` takes ``actions[:, action_map.indices] * scale`` and fits the rows to the chunk (slice, or pad
    according to ``pad_actions``).

    Server side (``from_family``, the inverse, used when serving one of our policies to an openpi-style client):
    images back to HWC uint8, placed at their view index into ``num_views`` views (views no key maps to are black),
    un-letterboxed and resized to ``our_image_size`` when given (else kept at the family size); state entries scattered
    back to their indices (divided by the scale; the first occurrence of a duplicated index wins) into ``state_dim``;
    the prompt looked up (case/space-insensitive) in the table to recover ``task`` (a fixed prompt or an unknown/missing
    prompt gives ``default_task``; unknown with ``default_task=None`` is an error). ``actions_to_family`` scatters our
    [chunk, 7] into zeros [chunk, family_dim].
    """
    name: str
    views: tuple[ViewField, ...]
    state: tuple[StateField, ...]
    action_map: ActionMap
    image_size: tuple[int, int] | None = (224, 224)
    resize: str = "pad"
    channels_first: bool = False
    prompt_key: KeyPath | None = "prompt"
    prompts: Mapping[int, str] | str | None = dataclasses.field(default_factory=lambda: dict(DEFAULT_PROMPTS))
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    pad_actions: str = "hold"
    view_names: tuple[str, ...] | None = None
    # inverse (server) side
    num_views: int = 3
    our_image_size: tuple[int, int] | None = None
    state_dim: int = 7
    default_task: int | None = None

    def replace(self, **changes: Any) -> "ObsMapping":
        return dataclasses.replace(self, **changes)

    # -- views ---------------------------------------------------------------------------------------------------------
    def _view_index(self, view: int | str, n: int) -> int:
        if isinstance(view, str):
            if not self.view_names or view not in self.view_names:
                raise KeyError(f"view {view!r} is not one of view_names={self.view_names}")
            view = self.view_names.index(view)
        if not -n <= view < n:
            raise IndexError(f"view index {view} out of range for {n} views (mapping {self.name!r})")
        return view % n

    def _image_out(self, img: np.ndarray) -> np.ndarray:
        img = _to_uint8(img)
        if self.image_size is not None:
            h, w = self.image_size
            if self.resize == "pad":
                img = resize_with_pad(img, h, w)
            elif self.resize == "stretch":
                img = _cv2_resize(img, h, w)
            else:
                raise ValueError(f"unknown resize {self.resize!r} (expected 'pad' or 'stretch')")
        if self.channels_first:
            img = np.transpose(img, (2, 0, 1))
        return np.ascontiguousarray(img)

    def _image_in(self, img: np.ndarray) -> np.ndarray:
        img = _to_uint8(img)
        if self.channels_first or (img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3):
            img = np.transpose(img, (1, 2, 0))
        if self.our_image_size is not None:
            h, w = self.our_image_size
            if self.image_size is not None and self.resize == "pad" and img.shape[:2] == tuple(self.image_size):
                top, left, rh, rw = _pad_box((h, w), img.shape[:2])
                img = img[top:top + rh, left:left + rw]
            img = _cv2_resize(img, h, w)
        return np.ascontiguousarray(img)

    # -- prompt --------------------------------------------------------------------------------------------------------
    def prompt_for(self, task: int) -> str | None:
        if self.prompts is None or isinstance(self.prompts, str):
            return self.prompts
        if task not in self.prompts:
            raise KeyError(f"no prompt for task id {task} in mapping {self.name!r} (known: {sorted(self.prompts)})")
        return self.prompts[task]

    def task_for(self, prompt: str | None) -> int:
        if isinstance(self.prompts, Mapping) and prompt is not None:
            norm = " ".join(str(prompt).split()).lower()
            for task, p in self.prompts.items():
                if " ".join(p.split()).lower() == norm:
                    return int(task)
        if self.default_task is not None:
            return self.default_task
        if not isinstance(self.prompts, Mapping):
            return 0
        raise ValueError(f"prompt {prompt!r} matches no task of mapping {self.name!r} "
                         f"(known prompts: {dict(self.prompts)}); set default_task to accept any prompt")

    # -- forward (client) ----------------------------------------------------------------------------------------------
    def to_family(self, obs: Mapping[str, Any]) -> dict:
        images = np.asarray(obs["images"])
        state = np.asarray(obs["state"], np.float32)
        out: dict = {}
        for vf in self.views:
            _put(out, vf.key, self._image_out(images[self._view_index(vf.view, images.shape[0])]))
        for sf in self.state:
            v = state[list(sf.indices)]
            if sf.scale is not None:
                v = v * np.asarray(sf.scale, np.float32)
            if sf.pad_to is not None and sf.pad_to > v.shape[0]:
                v = np.concatenate([v, np.zeros(sf.pad_to - v.shape[0], np.float32)])
            _put(out, sf.key, v.astype(np.float32))
        if self.prompt_key is not None:
            prompt = self.prompt_for(int(np.asarray(obs.get("task", 0))))
            if prompt is not None:
                _put(out, self.prompt_key, prompt)
        for k, v in self.extra.items():
            _put(out, k, v)
        return out

    def actions_to_ours(self, actions: np.ndarray, chunk: int) -> np.ndarray:
        actions = np.asarray(actions, np.float32)
        if actions.ndim != 2:
            raise ValueError(f"expected 'actions' of shape [H, D], got {actions.shape}")
        if max(self.action_map.indices) >= actions.shape[1]:
            raise ValueError(f"'actions' has D={actions.shape[1]} but mapping {self.name!r} reads dims "
                             f"{self.action_map.indices}")
        ours = actions[:, list(self.action_map.indices)]
        if self.action_map.scale is not None:
            ours = ours * np.asarray(self.action_map.scale, np.float32)
        return np.ascontiguousarray(_fit_rows(ours, chunk, self.pad_actions, f"policy ({self.name})"), np.float32)

    # -- inverse (server) ----------------------------------------------------------------------------------------------
    def from_family(self, fobs: Mapping[str, Any]) -> dict:
        views: list[np.ndarray | None] = [None] * self.num_views
        for vf in self.views:
            if _has(fobs, vf.key):
                views[self._view_index(vf.view, self.num_views)] = self._image_in(np.asarray(_get(fobs, vf.key)))
        present = [v for v in views if v is not None]
        if not present:
            raise KeyError(f"observation has none of the image keys of mapping {self.name!r}: "
                           f"{[vf.key for vf in self.views]} (got keys {sorted(map(str, fobs))})")
        if len({v.shape for v in present}) != 1:
            raise ValueError(f"views have different shapes {[v.shape for v in present]}; set our_image_size")
        images = np.stack([v if v is not None else np.zeros_like(present[0]) for v in views])
        state = np.zeros(self.state_dim, np.float32)
        filled = np.zeros(self.state_dim, bool)
        for sf in self.state:
            if not _has(fobs, sf.key):
                continue
            v = np.asarray(_get(fobs, sf.key), np.float32).reshape(-1)
            for j, i in enumerate(sf.indices):
                if j < v.shape[0] and not filled[i]:
                    state[i] = v[j] / (sf.scale[j] if sf.scale is not None else 1.0)
                    filled[i] = True
        prompt = _get(fobs, self.prompt_key) if self.prompt_key is not None and _has(fobs, self.prompt_key) else None
        return {"images": images, "state": state, "task": np.asarray(self.task_for(prompt), np.int32)}

    def actions_to_family(self, actions: np.ndarray) -> np.ndarray:
        actions = np.asarray(actions, np.float32)
        out = np.zeros((actions.shape[0], self.action_map.family_dim), np.float32)
        vals = actions[:, : len(self.action_map.indices)]
        if self.action_map.scale is not None:
            vals = vals / np.asarray(self.action_map.scale, np.float32)
        for j, i in reversed(list(enumerate(self.action_map.indices))):  # first occurrence wins
            out[:, i] = vals[:, j]
        return out


# DROID (pi0/pi0-FAST/pi05 _droid): two 224x224 HWC images, joint_position [7], gripper_position [1], actions [H, 8]
# (7 joint velocities + gripper). Our state[0:6] (EE pose) -> joint_position (zero-padded to 7), state[6] -> gripper;
# our 7 actions <- action dims 0..5 and 7 (the gripper).
DROID = ObsMapping(
    name="droid",
    views=(ViewField("observation/exterior_image_1_left", 0), ViewField("observation/wrist_image_left", -1)),
    state=(StateField("observation/joint_position", (0, 1, 2, 3, 4, 5), pad_to=7),
           StateField("observation/gripper_position", (6,))),
    action_map=ActionMap(family_dim=8, indices=(0, 1, 2, 3, 4, 5, 7)),
)
# LIBERO (pi0/pi05 _libero): 224x224 HWC images, state [8] = EE pos (3), axis-angle (3), gripper qpos (2, the two
# fingers +g / -g), actions [H, 7] delta EE + gripper, the same layout as ours. (openpi's LIBERO example also rotates
# the simulator's images by 180 degrees; do that before the mapping if your renders need it.)
LIBERO = ObsMapping(
    name="libero",
    views=(ViewField("observation/image", 0), ViewField("observation/wrist_image", -1)),
    state=(StateField("observation/state", (0, 1, 2, 3, 4, 5, 6, 6), scale=(1, 1, 1, 1, 1, 1, 1, -1)),),
    action_map=ActionMap(family_dim=7),
)
# ALOHA (pi0/pi05 _aloha*): images {cam_high, cam_low, cam_left_wrist[, cam_right_wrist]} CHW uint8 (openpi's ALOHA
# client letterboxes to 224x224 first), state [14] (two arms x (6 joints + gripper)), actions [H, 14]. We fill the
# left arm with our 7 numbers; cam_right_wrist is omitted (openpi's AlohaInputs substitutes a masked blank image).
ALOHA = ObsMapping(
    name="aloha",
    views=(ViewField(("images", "cam_high"), 0), ViewField(("images", "cam_low"), 1),
           ViewField(("images", "cam_left_wrist"), -1)),
    state=(StateField("state", (0, 1, 2, 3, 4, 5, 6), pad_to=14),),
    action_map=ActionMap(family_dim=14),
    channels_first=True,
)
PRESETS: dict[str, ObsMapping] = {"droid": DROID, "libero": LIBERO, "aloha": ALOHA}


def get_mapping(family: str | ObsMapping | None) -> ObsMapping | None:
    """A preset by name ("droid", "libero", "aloha"; "native" or None: no mapping), or the mapping itself."""
    if family is None or isinstance(family, ObsMapping):
        return family
    if family.lower() == "native":
        return None
    try:
        return PRESETS[family.lower()]
    except KeyError:
        raise ValueError(f"unknown policy family {family!r}; expected one of native, {', '.join(PRESETS)}") from None


# ----------------------------------------------------------------------------------------------------------------------
# Client
# ----------------------------------------------------------------------------------------------------------------------
class PolicyServerError(RuntimeError):
    """The policy server reported an error (a text frame with its traceback)."""


class PolicyConnectionError(ConnectionError):
    """Could not (re)connect to the policy server within the retry budget."""


class PolicyTimeoutError(TimeoutError):
    """The policy server did not answer in time."""


# websockets >= 17 warns unless a directly-returned connection is requested explicitly (older versions lack the flag).
_CONNECT_KW = {"legacy": True} if "legacy" in inspect.signature(websockets.sync.client.connect).parameters else {}


def _retriable(exc: BaseException) -> bool:
    if isinstance(exc, websockets.exceptions.InvalidStatus):
        return exc.response.status_code >= 500  # 503 while a server restarts; 401/403/404 will not get better
    if isinstance(exc, websockets.exceptions.InvalidURI):
        return False
    return isinstance(exc, (OSError, websockets.exceptions.WebSocketException))  # refused, reset, timeout, closed


class WebsocketClientPolicy:
    """A :class:`HostPolicy` backed by an openpi-protocol policy server (openpi's ``serve_policy.py`` or ours).

    ``infer(obs)`` maps our observation with ``mapping`` (a preset name or :class:`ObsMapping`; None = native: our
    dict as is), sends it, and maps the reply's ``"actions"`` back to float32 [chunk, 7]. ``infer_raw(dict) -> dict``
    speaks the protocol without any mapping. ``last_response`` holds the last raw reply (timings etc.).

    Connection failures (refused, reset, 5xx during the handshake, connection lost between requests) are retried
    ``max_retries`` times with exponential back-off ``backoff_s * 2**i`` (capped at ``max_backoff_s``), then raise
    :class:`PolicyConnectionError` naming ``host:port``. ``timeout_s`` bounds the opening handshake and each reply
    (:class:`PolicyTimeoutError`; the connection is dropped and re-opened by the next call). A text frame from the
    server raises :class:`PolicyServerError` with the server's traceback.
    """

    def __init__(self, host: str = "127.0.0.1", port: int | None = 8000, mapping: ObsMapping | str | None = None,
                 api_key: str | None = None, *, chunk: int | None = None, timeout_s: float = 60.0,
                 max_retries: int = 5, backoff_s: float = 0.5, max_backoff_s: float = 10.0):
        self.uri = host if host.startswith(("ws://", "wss://")) else f"ws://{host}"
        if port is not None:
            self.uri += f":{port}"
        self.address = self.uri.split("://", 1)[1]
        self.mapping = get_mapping(mapping)
        self.api_key, self.timeout_s = api_key, timeout_s
        self.max_retries, self.backoff_s, self.max_backoff_s = max_retries, backoff_s, max_backoff_s
        self._ws: websockets.sync.client.ClientConnection | None = None
        self._metadata: dict = {}
        self._lock = threading.Lock()
        self.last_response: dict | None = None
        self._connect()
        meta_chunk = self._metadata.get("chunk") if isinstance(self._metadata, dict) else None
        self.chunk = int(chunk if chunk is not None else meta_chunk if isinstance(meta_chunk, int) else DEFAULT_CHUNK)

    @property
    def metadata(self) -> dict:
        """The metadata dict the server sent on connect."""
        return self._metadata

    def get_server_metadata(self) -> dict:  # openpi_client spelling
        return self._metadata

    def _connect(self) -> None:
        self._close()
        headers = {"Authorization": f"Api-Key {self.api_key}"} if self.api_key else None
        last: BaseException | None = None
        for attempt in range(self.max_retries + 1):
            if attempt:
                delay = min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s)
                logger.info("policy server %s unreachable (%s); retry %d/%d in %.2fs", self.address, last, attempt,
                            self.max_retries, delay)
                time.sleep(delay)
            ws = None
            try:
                ws = websockets.sync.client.connect(self.uri, compression=None, max_size=None,
                                                    additional_headers=headers, open_timeout=self.timeout_s,
                                                    **_CONNECT_KW)
                first = ws.recv(timeout=self.timeout_s)
            except (OSError, websockets.exceptions.WebSocketException) as e:  # refused, reset, timeout, HTTP error
                if ws is not None:
                    ws.close()
                if not _retriable(e):
                    raise PolicyConnectionError(f"policy server at {self.address} refused the connection: "
                                                f"{type(e).__name__}: {e}") from e
                last = e
                continue
            if isinstance(first, str):
                ws.close()
                raise PolicyServerError(f"policy server at {self.address} sent an error instead of its metadata:\n"
                                        f"{first}")
            self._ws, self._metadata = ws, msgpack_numpy.unpackb(first)
            return
        raise PolicyConnectionError(f"could not connect to the policy server at {self.address} ({self.uri}) after "
                                    f"{self.max_retries + 1} attempts; last error: {type(last).__name__}: {last}")

    def _close(self) -> None:
        if self._ws is not None:
            try:
                self._ws.close()
            except Exception:  # noqa: BLE001
                pass
            self._ws = None

    def infer_raw(self, obs: Mapping[str, Any]) -> dict:
        """Send one observation dict as is and return the server's reply dict."""
        data = msgpack_numpy.packb(obs)
        with self._lock:
            last: BaseException | None = None
            for attempt in range(self.max_retries + 1):
                if self._ws is None:
                    if attempt:
                        time.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s))
                    self._connect()
                try:
                    self._ws.send(data)
                    reply = self._ws.recv(timeout=self.timeout_s)
                except TimeoutError as e:
                    self._close()  # a late reply would be read as the answer to the next request
                    raise PolicyTimeoutError(f"policy server at {self.address} did not answer within "
                                             f"{self.timeout_s}s") from e
                except websockets.exceptions.ConnectionClosed as e:
                    logger.warning("connection to policy server %s lost (%s); reconnecting", self.address, e)
                    self._close()
                    last = e
                    continue
                if isinstance(reply, str):
                    self._close()  # the server closes after an error frame
                    raise PolicyServerError(f"error in the policy server at {self.address}:\n{reply}")
                self.last_response = msgpack_numpy.unpackb(reply)
                return self.last_response
            raise PolicyConnectionError(f"lost the connection to the policy server at {self.address} "
                                        f"{self.max_retries + 1} times; last error: {last}")

    def infer(self, obs: Mapping[str, Any]) -> np.ndarray:
        """Our observation -> our action chunk float32 [chunk, 7]."""
        if self.mapping is None:
            reply = self.infer_raw({k: np.asarray(v) for k, v in obs.items()})
        else:
            reply = self.infer_raw(self.mapping.to_family(obs))
        if "actions" not in reply:
            raise PolicyServerError(f"reply from the policy server at {self.address} has no 'actions' "
                                    f"(keys: {sorted(map(str, reply))})")
        if self.mapping is None:
            actions = np.asarray(reply["actions"], np.float32)
            return np.ascontiguousarray(_fit_rows(actions, self.chunk, "hold", f"policy server {self.address}"))
        return self.mapping.actions_to_ours(reply["actions"], self.chunk)

    def reset(self) -> None:  # openpi_client API
        pass

    def close(self) -> None:
        self._close()

    def __enter__(self) -> "WebsocketClientPolicy":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# ----------------------------------------------------------------------------------------------------------------------
# Server
# ----------------------------------------------------------------------------------------------------------------------
class PolicyServer:
    """Serve one of our policies (a :class:`JaxPolicy`, wrapped with ``as_host``, or any :class:`HostPolicy`) over
    openpi's protocol, so openpi clients (``openpi_client.WebsocketClientPolicy``) or ours can query it.

    Requests are our observation dict (``mapping=None``) or a family's observation, mapped back with
    ``mapping.from_family``; the reply is ``{"actions": ..., "server_timing": {"infer_ms", "prev_total_ms"}}`` with
    actions mapped by ``mapping.actions_to_family``. A HostPolicy whose ``infer`` returns a dict is passed through
    (openpi-style policies). An exception inside the policy sends the traceback as a text frame and closes the
    connection with 1011, like openpi. ``GET /healthz`` -> 200 ``OK``. With ``api_key`` set, WebSocket connections
    must carry ``Authorization: Api-Key <key>`` (else 401). Inference is serialised with a lock (one policy, many
    connections). ``port=0`` binds a free port (see ``.port``). Use ``start()`` for a background thread and
    ``shutdown()`` to stop, or ``serve_forever()`` to block.
    """

    def __init__(self, policy: JaxPolicy | HostPolicy, host: str = "0.0.0.0", port: int = 8000,
                 metadata: Mapping[str, Any] | None = None, mapping: ObsMapping | str | None = None,
                 api_key: str | None = None):
        self.policy = as_host(policy) if isinstance(policy, JaxPolicy) else policy
        if not callable(getattr(self.policy, "infer", None)):
            raise TypeError(f"{type(policy).__name__} is neither a JaxPolicy nor a HostPolicy (no .infer)")
        self.mapping = get_mapping(mapping)
        self.api_key = api_key
        name = getattr(policy, "name", type(policy).__name__)
        chunk = getattr(self.policy, "chunk", None)
        self.metadata = {"server": "sc3_jax", "policy": str(name), "family": self.mapping.name if self.mapping else
                         "native", **({"chunk": int(chunk)} if isinstance(chunk, int) else {}),
                         **({"action_dim": self.mapping.action_map.family_dim} if self.mapping else {}),
                         **dict(metadata or {})}
        msgpack_numpy.packb(self.metadata)  # fail now, not on the first connection
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._serving = False
        self._stopped = False
        self._server = websockets.sync.server.serve(self._handler, host, port, compression=None, max_size=None,
                                                    process_request=self._process_request)
        self.host, self.port = self._server.socket.getsockname()[:2]

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        return f"ws://{host}:{self.port}"

    def _process_request(self, connection: Any, request: Any) -> Any:
        if request.path == "/healthz":
            return connection.respond(HTTPStatus.OK, "OK\n")
        if self.api_key and request.headers.get("Authorization") != f"Api-Key {self.api_key}":
            return connection.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong Authorization: Api-Key header\n")
        return None

    def _infer(self, obs: Any) -> dict:
        if not isinstance(obs, dict):
            raise TypeError(f"expected an observation dict, got {type(obs).__name__}")
        ours = self.mapping.from_family(obs) if self.mapping is not None else obs
        with self._lock:
            out = self.policy.infer(ours)
        if isinstance(out, Mapping):
            return dict(out)
        actions = np.asarray(out)
        if self.mapping is not None:
            actions = self.mapping.actions_to_family(actions)
        return {"actions": actions}

    def _handler(self, ws: websockets.sync.server.ServerConnection) -> None:
        try:
            ws.send(msgpack_numpy.packb(self.metadata))
        except websockets.exceptions.ConnectionClosed:
            return
        prev_total_ms = None
        while True:
            try:
                msg = ws.recv()
            except websockets.exceptions.ConnectionClosed:
                return
            start = time.monotonic()
            try:
                if isinstance(msg, str):
                    raise TypeError("expected a binary msgpack frame, got a text frame")
                obs = msgpack_numpy.unpackb(msg)
                t0 = time.monotonic()
                result = self._infer(obs)
                timing = {"infer_ms": (time.monotonic() - t0) * 1000.0}
                if prev_total_ms is not None:
                    timing["prev_total_ms"] = prev_total_ms
                result["server_timing"] = timing
                ws.send(msgpack_numpy.packb(result))
            except websockets.exceptions.ConnectionClosed:
                return
            except Exception:  # noqa: BLE001 - reported to the client, like openpi
                tb = traceback.format_exc()
                logger.error("policy inference failed:\n%s", tb)
                try:
                    ws.send(tb)
                    ws.close(CloseCode.INTERNAL_ERROR, "Internal server error. Traceback included in previous frame.")
                except websockets.exceptions.ConnectionClosed:
                    pass
                return
            prev_total_ms = (time.monotonic() - start) * 1000.0

    def serve_forever(self) -> None:
        self._serving = True
        self._server.serve_forever()

    def start(self) -> "PolicyServer":
        """Serve from a background (daemon) thread; returns self."""
        if self._thread is None:
            self._serving = True
            self._thread = threading.Thread(target=self._server.serve_forever, name=f"policy-server:{self.port}",
                                            daemon=True)
            self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop accepting connections, close open ones, wait for their handlers. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        if self._serving:
            self._server.shutdown()
        else:
            self._server.socket.close()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def __enter__(self) -> "PolicyServer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.shutdown()


def serve(policy: JaxPolicy | HostPolicy, host: str = "0.0.0.0", port: int = 8000,
          metadata: Mapping[str, Any] | None = None, mapping: ObsMapping | str | None = None, *,
          api_key: str | None = None, block: bool = True) -> PolicyServer:
    """Serve ``policy`` over openpi's protocol. ``block=True`` serves until KeyboardInterrupt (then shuts down);
    ``block=False`` starts a background thread and returns the running :class:`PolicyServer`."""
    server = PolicyServer(policy, host, port, metadata, mapping, api_key)
    if not block:
        return server.start()
    logger.info("serving %s on %s (family %s)", server.metadata.get("policy"), server.url, server.metadata["family"])
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
    return server


# ----------------------------------------------------------------------------------------------------------------------
# CLI: sc3 serve-policy
# ----------------------------------------------------------------------------------------------------------------------
def _load_policy(spec: str) -> JaxPolicy | HostPolicy:
    """``module:attr``: attr is a JaxPolicy / HostPolicy, or a zero-argument factory returning one."""
    if ":" not in spec:
        raise ValueError(f"--policy must look like 'package.module:attr', got {spec!r}")
    mod_name, attr = spec.split(":", 1)
    obj: Any = importlib.import_module(mod_name)
    for part in attr.split("."):
        obj = getattr(obj, part)
    if not isinstance(obj, JaxPolicy) and not callable(getattr(obj, "infer", None)):
        if not callable(obj):
            raise TypeError(f"{spec} is neither a policy nor a factory")
        obj = obj()
    if not isinstance(obj, JaxPolicy) and not callable(getattr(obj, "infer", None)):
        raise TypeError(f"{spec} produced {type(obj).__name__}, which is neither a JaxPolicy nor a HostPolicy")
    return obj


def _serve_policy_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sc3 serve-policy",
                                description="Serve one of our policies over openpi's WebSocket protocol.")
    p.add_argument("--policy", required=True, help="module:attr of a JaxPolicy/HostPolicy or a factory returning one")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=8000, help="0 = any free port (printed)")
    p.add_argument("--family", default="native", choices=["native", *PRESETS],
                   help="observation keys clients send (native = our own observation dict)")
    p.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="image size our policy expects (family images are un-letterboxed and resized to it)")
    p.add_argument("--num-views", type=int, default=3, help="number of views our policy expects")
    p.add_argument("--task-prompt", action="append", default=[], metavar="ID=PROMPT",
                   help="prompt -> task id table entry (repeatable); default: the bussing / reverse-bussing prompts")
    p.add_argument("--default-task", type=int, default=None, help="task id for prompts not in the table")
    p.add_argument("--api-key", default=None, help="require 'Authorization: Api-Key <key>'")
    p.add_argument("--log-level", default="INFO")
    return p


def build_policy_server(argv: Sequence[str] | None = None,
                        resolve: Callable[[str], JaxPolicy | HostPolicy] | None = None) -> PolicyServer:
    """Parse ``sc3 serve-policy`` arguments and return the (bound, not yet serving) :class:`PolicyServer`."""
    args = _serve_policy_parser().parse_args(list(argv) if argv is not None else None)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    policy = resolve(args.policy) if resolve is not None else _load_policy(args.policy)
    mapping = get_mapping(args.family)
    if mapping is not None:
        changes: dict[str, Any] = {"num_views": args.num_views, "default_task": args.default_task}
        if args.image_size:
            changes["our_image_size"] = tuple(args.image_size)
        if args.task_prompt:
            table = {}
            for entry in args.task_prompt:
                tid, sep, prompt = entry.partition("=")
                if not sep:
                    raise ValueError(f"--task-prompt expects ID=PROMPT, got {entry!r}")
                table[int(tid)] = prompt
            changes["prompts"] = table
        mapping = mapping.replace(**changes)
    return PolicyServer(policy, args.host, args.port, None, mapping, args.api_key)


def serve_policy_main(argv: Sequence[str] | None = None,
                      resolve: Callable[[str], JaxPolicy | HostPolicy] | None = None) -> int:
    """``sc3 serve-policy --policy module:attr [--family droid] [--port 8000] ...``: serve one of our policies over
    openpi's protocol until interrupted (Ctrl-C). ``resolve`` (optional) turns the ``--policy`` string into a policy
    instead of importing ``module:attr`` (attr: a JaxPolicy / HostPolicy, or a zero-argument factory of one)."""
    server = build_policy_server(argv, resolve)
    print(f"serving {server.metadata['policy']} on {server.url} (family {server.metadata['family']}); "
          f"health check: http://{server.url.split('://', 1)[1]}/healthz", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
    return 0
