"""openpi policy families' observation and action keys <-> ours: :class:`ObsMapping` and the presets :data:`DROID`,
:data:`LIBERO`, :data:`ALOHA` (``mapping=None``, "native", sends our observation dict unchanged). Used by the client
(``openpi_client.py``) to query a family's server and by our server (``openpi_server.py``) to answer its clients.

Our observation is ``{"images": uint8 [V,H,W,3], "state": float32 [S], "task": int32 []}`` (see ``base.py``), our
action chunk float32 [chunk, D]; a family's are its own keys and ``"actions"`` [H, D_family].

The robot's state/action layout is the model's, not fixed to our 7-D delta-EE benchmark: each preset says which
layout it carries and checks it (:meth:`ObsMapping.check_dims`), so a model of the wrong dimension fails loudly
instead of silently losing dims. DROID and ALOHA are identities over openpi's own layouts (an 8-D DROID model:
7 joint velocities + gripper position, state 7 joint positions + gripper; a 14-D ALOHA model: [left 6 joints,
left gripper, right 6 joints, right gripper] joint positions, in the standard ALOHA runtime space, which openpi's
``AlohaInputs(adapt_to_pi=True)`` converts itself). LIBERO maps our 7-D EE pose + gripper / delta-EE actions, the
layout of our own benchmark. Conventions checked against openpi's files listed in docs/openpi.md.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

__all__ = ["ViewField", "StateField", "ActionMap", "ObsMapping", "DROID", "LIBERO", "ALOHA", "ALOHA_CAMERAS",
           "PRESETS", "DEFAULT_PROMPTS", "get_mapping", "resize_with_pad"]

DEFAULT_PROMPTS: dict[int, str] = {
    0: "put the utensils in the bin and the trash in the trash can",  # bussing (in-distribution)
    1: "put the utensils in the trash can and the trash in the bin",  # reverse bussing (out-of-distribution)
}

KeyPath = str | tuple[str, ...]  # a tuple addresses a nested dict, e.g. ("images", "cam_high")


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
    ``"actions"`` [H, D] (used when serving: family dims we do not produce are zero). ``indices=None``: all
    ``family_dim`` dims in order, so our action dimension is the family's."""
    family_dim: int
    indices: tuple[int, ...] | None = None
    scale: tuple[float, ...] | None = None

    @property
    def our_indices(self) -> tuple[int, ...]:
        return tuple(range(self.family_dim)) if self.indices is None else tuple(self.indices)


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


def fit_rows(actions: np.ndarray, chunk: int, pad: str, where: str) -> np.ndarray:
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
    [chunk, D] into zeros [chunk, family_dim].

    Dimensions: our action dimension is ``len(action_map.our_indices)``; our state dimension ``state_dim`` (None:
    the highest mapped state index + 1, not enforced on the client). Both sides refuse other dimensions with a
    ValueError (see :meth:`check_dims`) rather than dropping or inventing dims.
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
    state_dim: int | None = None
    default_task: int | None = None

    def replace(self, **changes: Any) -> "ObsMapping":
        return dataclasses.replace(self, **changes)

    # -- dimensions ----------------------------------------------------------------------------------------------------
    @property
    def action_dim(self) -> int:
        """Our action dimension under this mapping."""
        return len(self.action_map.our_indices)

    @property
    def our_state_dim(self) -> int:
        return self.state_dim if self.state_dim is not None else max(max(sf.indices) + 1 for sf in self.state)

    def check_dims(self, action_dim: int | None = None, state_dim: int | None = None, who: str = "the model") -> None:
        """One-line ValueError when ``who``'s action/state dimension is not the one this mapping carries (e.g. a 7-D
        model with the 14-D bimanual ALOHA preset would otherwise silently drive one arm)."""
        for kind, got, want in (("action", action_dim, self.action_dim), ("state", state_dim, self.state_dim)):
            if got is not None and want is not None and int(got) != want:
                raise ValueError(f"openpi mapping {self.name!r} carries {want}-D {kind}s but {who} has {int(got)}-D "
                                 f"{kind}s; use a {want}-D model or a mapping for {int(got)}-D {kind}s")

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
        self.check_dims(state_dim=state.shape[-1], who="the observation")
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
        idx = self.action_map.our_indices
        if max(idx) >= actions.shape[1]:
            raise ValueError(f"'actions' has D={actions.shape[1]} but mapping {self.name!r} reads dims {idx}")
        ours = actions[:, list(idx)]
        if self.action_map.scale is not None:
            ours = ours * np.asarray(self.action_map.scale, np.float32)
        return np.ascontiguousarray(fit_rows(ours, chunk, self.pad_actions, f"policy ({self.name})"), np.float32)

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
        state = np.zeros(self.our_state_dim, np.float32)
        filled = np.zeros(self.our_state_dim, bool)
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
        if actions.ndim != 2:
            raise ValueError(f"expected our actions of shape [chunk, D], got {actions.shape}")
        self.check_dims(action_dim=actions.shape[1], who="the policy's action chunk")
        out = np.zeros((actions.shape[0], self.action_map.family_dim), np.float32)
        vals = actions
        if self.action_map.scale is not None:
            vals = vals / np.asarray(self.action_map.scale, np.float32)
        for j, i in reversed(list(enumerate(self.action_map.our_indices))):  # first occurrence wins
            out[:, i] = vals[:, j]
        return out


# DROID (openpi src/openpi/policies/droid_policy.py, examples/droid/main.py; pi0/pi0-FAST/pi05 _droid): two HWC uint8
# images letterboxed to 224x224 (the DROID client resizes with pad before sending), state joint_position [7] +
# gripper_position [1], actions [H, 8] = 7 joint velocities + gripper position (DroidOutputs keeps the first 8 dims).
# Our robot is a DROID Franka: an 8-D model, state [7 joint positions, gripper], views in DROID dataset order
# (exterior 1, exterior 2, wrist; openpi's policies take exterior 1 and the wrist only).
DROID = ObsMapping(
    name="droid",
    views=(ViewField("observation/exterior_image_1_left", 0), ViewField("observation/wrist_image_left", -1)),
    state=(StateField("observation/joint_position", tuple(range(7))),
           StateField("observation/gripper_position", (7,))),
    action_map=ActionMap(family_dim=8),
    state_dim=8,
)
# LIBERO (pi0/pi05 _libero): 224x224 HWC images, state [8] = EE pos (3), axis-angle (3), gripper qpos (2, the two
# fingers +g / -g), actions [H, 7] delta EE + gripper, the same layout as our 7-D benchmark. (openpi's LIBERO example
# also rotates the simulator's images by 180 degrees; do that before the mapping if your renders need it.)
LIBERO = ObsMapping(
    name="libero",
    views=(ViewField("observation/image", 0), ViewField("observation/wrist_image", -1)),
    state=(StateField("observation/state", (0, 1, 2, 3, 4, 5, 6, 6), scale=(1, 1, 1, 1, 1, 1, 1, -1)),),
    action_map=ActionMap(family_dim=7),
    state_dim=7,
)
# ALOHA (openpi src/openpi/policies/aloha_policy.py, examples/aloha_real/{env,real_env}.py; pi0/pi05 _aloha*): images
# {cam_high, cam_low, cam_left_wrist, cam_right_wrist} as CHW uint8 letterboxed to 224x224 (the ALOHA client's
# resize_with_pad + "h w c -> c h w"), state [14] and actions [H, 14] = [left 6 joints, left gripper, right 6 joints,
# right gripper] (AlohaOutputs keeps the first 14 dims). Our robot is a bimanual ALOHA: a 14-D model, 4 views in
# that camera order.
ALOHA_CAMERAS = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
ALOHA = ObsMapping(
    name="aloha",
    views=tuple(ViewField(("images", cam), cam) for cam in ALOHA_CAMERAS),
    state=(StateField("state", tuple(range(14))),),
    action_map=ActionMap(family_dim=14),
    channels_first=True,
    view_names=ALOHA_CAMERAS,
    num_views=4,
    state_dim=14,
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
