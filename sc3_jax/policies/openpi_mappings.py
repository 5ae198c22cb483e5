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
layout of our own benchmark. Conventions checked against openpi's files listed in docs/openpi.md (commit 15a9616).

What runs where (openpi's convention, which the presets keep): the *client* letterboxes each camera to 224x224 uint8
(and, for ALOHA, transposes to CHW) and sends the robot's raw state; the *server* (openpi's ``serve_policy.py``)
does everything else: ``AlohaInputs/Outputs(adapt_to_pi)`` joint flips and gripper conversions, delta <-> absolute
actions, normalisation, its own resize to 224, the default prompt when none is sent, and cutting the model's 32
action dims to the family's (8 DROID, 14 ALOHA, 7 LIBERO). So the presets send raw robot values and read back the
family's actions unchanged.

Dimension mismatches (a 7-D model with the 14-D ALOHA preset, 3 views for its 4 cameras, a 7-entry state) are a
one-line :class:`~sc3_jax.core.errors.UserError` naming both sides (:meth:`ObsMapping.check_dims`).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from sc3_jax.core.errors import UserError

__all__ = ["ViewField", "StateField", "ActionMap", "ObsMapping", "DROID", "LIBERO", "ALOHA", "ALOHA_CAMERAS",
           "PRESETS", "get_mapping", "for_world_model", "resize_with_pad"]

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
        raise UserError(f"{where} returned {h} actions but a chunk of {chunk} is needed (pad_actions={pad!r}); ask "
                        f"for chunk <= {h}, or set pad_actions='hold' to repeat the last action")
    if pad == "hold":
        fill = np.repeat(actions[-1:], chunk - h, axis=0)
    elif pad == "zeros":
        fill = np.zeros((chunk - h, *actions.shape[1:]), actions.dtype)
    else:
        raise UserError(f"unknown pad_actions {pad!r} (expected 'hold', 'zeros' or 'error')")
    return np.concatenate([actions, fill], axis=0)


@dataclasses.dataclass(frozen=True)
class ObsMapping:
    """Our observation <-> an openpi policy family's observation, and our action chunk <-> the family's actions.

    Client side (``to_family``): each :class:`ViewField` picks one of our views, resizes it to ``image_size``
    (``resize="pad"``: openpi's keep-aspect letterbox; ``"stretch"``: plain resize; ``image_size=None``: as is) and
    transposes it to CHW when ``channels_first``; each :class:`StateField` slices/scales/pads ``state``; the prompt is
    ``prompts[task]`` (a task-id -> prompt table: each episode's own instruction, or a benchmark's
    ``Benchmark.prompts``) or ``prompts`` itself when it is a string (fixed prompt; None, the default: no prompt key,
    so the server's default prompt applies). ``extra`` entries are sent unchanged with every request.
    ``actions_to_ours`` takes ``actions[:, action_map.indices] * scale`` and fits the rows to the chunk (slice, or pad
    according to ``pad_actions``). ``chunk``: the actions our client executes per request when neither the caller
    nor the server's metadata says (a preset's is its openpi example client's; None: the client's default, 25).

    Server side (``from_family``, the inverse, used when serving one of our policies to an openpi-style client):
    images back to HWC uint8, placed at their view index into ``num_views`` views (views no key maps to are black),
    un-letterboxed and resized to ``our_image_size`` when given (else kept at the family size); state entries scattered
    back to their indices (divided by the scale; the first occurrence of a duplicated index wins) into ``state_dim``;
    the prompt looked up (case/space-insensitive) in the table to recover ``task`` (a fixed prompt or an unknown/missing
    prompt gives ``default_task``; unknown with ``default_task=None`` is an error; no table: ``default_task``, else
    0). ``actions_to_family`` scatters our [chunk, D] into zeros [chunk, family_dim].

    Dimensions: our action dimension is ``len(action_map.our_indices)``; our state dimension ``state_dim`` (None:
    the highest mapped state index + 1, not enforced on the client); our views at least :attr:`min_views`. Both sides
    refuse other dimensions with a one-line UserError (a ValueError; see :meth:`check_dims`) rather than dropping or
    inventing dims.
    """
    name: str
    views: tuple[ViewField, ...]
    state: tuple[StateField, ...]
    action_map: ActionMap
    image_size: tuple[int, int] | None = (224, 224)
    resize: str = "pad"
    channels_first: bool = False
    prompt_key: KeyPath | None = "prompt"
    prompts: Mapping[int, str] | str | None = None  # the instructions are the episodes' or a benchmark's, not ours
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    pad_actions: str = "hold"
    chunk: int | None = None
    view_names: tuple[str, ...] | None = None
    # inverse (server) side
    num_views: int = 3
    our_image_size: tuple[int, int] | None = None
    state_dim: int | None = None
    default_task: int | None = None

    def __post_init__(self) -> None:
        # checked here so that a wrong preset edit (serve-policy --num-views 3 --family aloha) fails at start
        if self.resize not in ("pad", "stretch"):
            raise UserError(f"openpi mapping {self.name!r}: resize={self.resize!r}, expected 'pad' or 'stretch'")
        if self.pad_actions not in ("hold", "zeros", "error"):
            raise UserError(f"openpi mapping {self.name!r}: pad_actions={self.pad_actions!r}, expected 'hold', "
                            "'zeros' or 'error'")
        if self.chunk is not None and self.chunk < 1:
            raise UserError(f"openpi mapping {self.name!r}: chunk={self.chunk}, expected a positive number of actions")
        for vf in self.views:
            if isinstance(vf.view, str) and (not self.view_names or vf.view not in self.view_names):
                raise UserError(f"openpi mapping {self.name!r}: view {vf.view!r} of key {vf.key!r} is not one of "
                                f"view_names={self.view_names}")
        if self.num_views < self.min_views:
            raise UserError(f"openpi mapping {self.name!r} sends {len(self.views)} cameras ({self._cameras()}) read "
                            f"from {self.min_views} views but num_views is {self.num_views}; set num_views >= "
                            f"{self.min_views}")

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

    @property
    def min_views(self) -> int:
        """How many of our views an observation needs: views counted from the front (0, 1, ...) and from the back
        (-1 = the wrist, ...) must not overlap, so DROID's view 0 + view -1 needs 2 and ALOHA's 4 cameras need 4."""
        front = [self.view_names.index(v) if isinstance(v, str) else v for v in (vf.view for vf in self.views)]
        return max([i + 1 for i in front if i >= 0] or [0]) + max([-i for i in front if i < 0] or [0])

    def _cameras(self) -> str:
        return ", ".join((vf.key if isinstance(vf.key, str) else vf.key[-1]) for vf in self.views)

    def check_dims(self, action_dim: int | None = None, state_dim: int | None = None, views: int | None = None,
                   who: str = "the model") -> None:
        """One-line UserError naming both sides when ``who``'s action / state dimension is not the one this mapping
        carries, or it has fewer views than the mapping's cameras read (e.g. a 7-D model, or 3 views, with the
        14-D, 4-camera ALOHA preset would otherwise silently drive one arm / send a wrong camera)."""
        for kind, got, want in (("action", action_dim, self.action_dim), ("state", state_dim, self.state_dim)):
            if got is not None and want is not None and int(got) != want:
                raise UserError(f"openpi mapping {self.name!r} carries {want}-D {kind}s but {who} has {int(got)}-D "
                                f"{kind}s; use a {want}-D model or a mapping for {int(got)}-D {kind}s")
        if views is not None and int(views) < self.min_views:
            raise UserError(f"openpi mapping {self.name!r} sends {len(self.views)} cameras ({self._cameras()}) read "
                            f"from {self.min_views} views but {who} has {int(views)} views; use a "
                            f"{self.min_views}-view model or a mapping with fewer cameras")

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
        if images.ndim != 4:
            raise UserError(f"openpi mapping {self.name!r} takes images [V, H, W, 3], the observation has "
                            f"{list(images.shape)}")
        self.check_dims(state_dim=state.shape[-1], views=images.shape[0], who="the observation")
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
            raise UserError(f"the policy server returned actions [{actions.shape[0]}, {actions.shape[1]}] but openpi "
                            f"mapping {self.name!r} reads {self.action_map.family_dim}-D actions (dims up to "
                            f"{max(idx)}); serve a {self.action_map.family_dim}-D policy or use its family's mapping")
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
            if not len(sf.indices) <= v.shape[0] <= max(len(sf.indices), sf.pad_to or 0):
                raise UserError(f"the client sent {sf.key!r} with {v.shape[0]} entries but openpi mapping "
                                f"{self.name!r} reads {len(sf.indices)}; send the family's full state")
            for j, i in enumerate(sf.indices):
                if not filled[i]:
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


# DROID (openpi@15a9616 src/openpi/policies/droid_policy.py, examples/droid/main.py, training/config.py pi0_droid /
# pi0_fast_droid / pi05_droid): HWC uint8 images letterboxed to 224x224 by the client (main.py's resize_with_pad), the
# chosen exterior camera as "observation/exterior_image_1_left" and the wrist as "observation/wrist_image_left" (the
# left image of each stereo pair; DroidInputs reads no other camera), state "observation/joint_position" [7] +
# "observation/gripper_position" [1], "prompt". The reply is actions [H, 8] = 7 joint velocities + gripper position
# (DroidOutputs keeps the first 8 of the model's dims; H = 10 for pi0 / pi0-FAST, 15 for pi05), of which main.py
# executes 8 (open_loop_horizon) before asking again: our chunk. A shorter reply is an error, not padded: holding a
# joint velocity keeps the arm moving. (main.py also binarises the gripper at 0.5 and clips to [-1, 1] before
# env.step: the robot's job, not the mapping's.) Our robot is a DROID Franka: an 8-D model, state [7 joint positions,
# gripper], views in DROID dataset order (exterior 1, exterior 2, wrist; view 0 and the last view are sent).
DROID = ObsMapping(
    name="droid",
    views=(ViewField("observation/exterior_image_1_left", 0), ViewField("observation/wrist_image_left", -1)),
    state=(StateField("observation/joint_position", tuple(range(7))),
           StateField("observation/gripper_position", (7,))),
    action_map=ActionMap(family_dim=8),
    pad_actions="error",
    chunk=8,
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
# ALOHA (openpi@15a9616 src/openpi/policies/aloha_policy.py, examples/aloha_real/{main,env,real_env}.py,
# training/config.py pi0_aloha / pi05_aloha / pi0_aloha_*): "images" {cam_high, cam_low, cam_left_wrist,
# cam_right_wrist} as CHW uint8 letterboxed to 224x224 by the client (env.py: resize_with_pad, convert_to_uint8,
# "h w c -> c h w"; AlohaInputs.EXPECTED_CAMERAS; pi0/pi05 read cam_high and the two wrists, cam_low is accepted),
# "state" [14] = the robot's qpos [left 6 joints, left gripper, right 6 joints, right gripper] in the standard ALOHA
# space (real_env.py; the joint flips and gripper conversions of adapt_to_pi run in the server), and "prompt" (env.py
# sends none and leaves it to the config's default_prompt; pi0_aloha / pi05_aloha have none and need one: pass
# prompts=None for a server whose config has one). The reply is actions [H, 14] in the same layout, absolute joint
# targets (AlohaOutputs keeps the first 14 dims; the server turns its delta joints back to absolute; H = 50), of which
# main.py executes 25 (action_horizon): our chunk. Our robot is a bimanual ALOHA: a 14-D model, 4 views in that camera
# order.
ALOHA_CAMERAS = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
ALOHA = ObsMapping(
    name="aloha",
    views=tuple(ViewField(("images", cam), cam) for cam in ALOHA_CAMERAS),
    state=(StateField("state", tuple(range(14))),),
    action_map=ActionMap(family_dim=14),
    channels_first=True,
    chunk=25,
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
        raise UserError(f"unknown policy family {family!r}; expected one of native, {', '.join(PRESETS)}") from None


def for_world_model(family: str | ObsMapping | None, views: tuple[str, ...], prompts: list[str], what: str):
    """The openpi ``family``'s mapping (None: native) for a world model with ``views``, prompting with ``prompts``
    (task id i -> prompts[i], e.g. each held-out episode's own instruction; an empty one sends no prompt, so the
    server's default applies). Cameras named by the preset are taken by the model's view names when it has them all
    (an ALOHA dataset's cam_high, ...), else by position; a view it cannot have is refused here (``what``: the
    option that chose the family, for the message), not at the first chunk."""
    m = get_mapping(family)
    if m is None:
        return None
    names = [vf.view for vf in m.views if isinstance(vf.view, str)]
    if names and set(names) <= set(views):
        m = m.replace(view_names=tuple(views), num_views=len(views))
    want = [m.view_names.index(v) if isinstance(v, str) else v for v in (vf.view for vf in m.views)]
    if any(not -len(views) <= i < len(views) for i in want):
        keys = [vf.key if isinstance(vf.key, str) else "/".join(vf.key) for vf in m.views]
        raise UserError(f"{what}: openpi's {m.name} layout sends {len(keys)} cameras {keys}; the world model has "
                        f"{len(views)} views {list(views)}")
    return m.replace(prompts={i: p or None for i, p in enumerate(prompts)})
