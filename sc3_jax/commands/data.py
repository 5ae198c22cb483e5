"""``sc3 data SUBCOMMAND ...``: convert between LeRobot datasets and our episode store (docs/lerobot.md).

    sc3 data import-lerobot --data ROOT --out DIR [--views VIEW[=KEY] ...] [--wrist VIEW ...] [--fps N]
                            [--image-size H W] [--action-key KEY] [--pose-key KEY] [--allow-missing-pose]
    sc3 data export-lerobot --data STORE --out DIR [--version v3.0|v2.1] [--codec h264|av1] [--crf N]
                            [--images video|image] [--views VIEW ...] [--overwrite]

``--views left=observation.images.cam_high`` names a camera key as one of our views; a bare ``cam_high`` keeps its
name (``observation.images.`` is implied). Views listed in ``--wrist`` are wrist cameras, the rest third-person
(default: names containing "wrist"). The conversions themselves are ``data/lerobot_import.py`` and
``data/lerobot_write.py``.
"""
from __future__ import annotations

import dataclasses
from typing import Annotated, Literal

import tyro

from sc3_jax.commands import run_group
from sc3_jax.core.errors import UserError

SUMMARY = "LeRobot datasets to and from our episode store"  # the line `sc3 --help` shows
# the line Ctrl-C ends with (cli.py; every writer is atomic)
RESUME = "the same command resumes it (imported episodes are kept)"


@dataclasses.dataclass(frozen=True)
class ImportLerobot:
    """LeRobot dataset (v2.x / v3.0) -> our episode store; resumable (episodes already in --out are skipped)."""

    data: str
    """the LeRobot dataset's directory (holding meta/info.json)"""
    out: str
    """episode store to write (created if missing)"""
    views: Annotated[tuple[str, ...] | None, tyro.conf.arg(metavar="VIEW[=KEY] ...")] = None
    """cameras to import, in our view order: VIEW (the key observation.images.VIEW) or VIEW=FEATURE_KEY (None:
    every camera, named after its key)"""
    wrist: Annotated[tuple[str, ...] | None, tyro.conf.arg(metavar="VIEW ...")] = None
    """which of our views are wrist cameras (None: those whose name contains "wrist")"""
    fps: float | None = None
    """subsample to this rate (an integer ratio to the dataset's fps; default: the dataset's)"""
    image_size: Annotated[tuple[int, int] | None, tyro.conf.arg(metavar="H W")] = None
    """resize every view to this height and width (needed when the cameras' sizes differ)"""
    action_key: str = "action"
    """the feature that becomes our actions"""
    pose_key: str = "observation.state"
    """the 7-D feature that becomes our ee_pose"""
    allow_missing_pose: bool = False
    """import delta_ee actions without a 7-D --pose-key: the store then has no ee_pose (no pseudo-actions)"""
    action_space: Literal["delta_ee", "absolute", "velocity"] | None = None
    """what the actions are (data/action_space.py): delta_ee (xyz, rotation vector, gripper: 7-D), absolute
    (joint or end-effector targets) or velocity (None: the dataset's sc3_action_space entry if it has one, else
    delta_ee for 7-D actions; other actions need this)"""
    action_names: tuple[str, ...] | None = None
    """one name per action dimension (None: the action feature's own names)"""
    action_targets: tuple[int, ...] | None = None
    """with --action-space velocity: the indices of dimensions that are position targets (e.g. a gripper)"""
    state_key: str = "auto"
    """the proprioceptive state feature, of any size, stored as the episodes' state ("auto":
    observation.state when present and not already the ee_pose; "none": no state)"""
    episodes: Annotated[tuple[str, ...] | None, tyro.conf.arg(metavar="A:B|N ...")] = None
    """which episodes (the dataset's episode_index) to import: ranges A:B (B excluded, either end open) or single
    indices, e.g. `--episodes 0:20` for a training store and `--episodes 20:` for a held-out one (None: all); an
    index of a closed range or a single one that the dataset lacks is refused"""
    id_prefix: str = ""
    """put in front of the episode ids (PREFIXlerobot000012): one store holds several datasets (recording
    sessions) under a prefix each"""


@dataclasses.dataclass(frozen=True)
class ExportLerobot:
    """Our episode store -> LeRobot dataset (actions -> action, the state (else ee_pose) -> observation.state,
    prompt -> task; the action space in info.json)."""

    data: str
    """the episode store to export (a directory holding dataset.json)"""
    out: str
    """LeRobot dataset directory to write"""
    version: Literal["v3.0", "v2.1"] = "v3.0"
    """LeRobot dataset format version"""
    codec: Literal["h264", "av1"] = "h264"
    """video codec of the mp4s"""
    crf: int | None = None
    """video quality, lower is better (None: 18 for h264, 30 for av1)"""
    images: Literal["video", "image"] = "video"
    """mp4 videos, or PNGs inside the parquet files"""
    views: Annotated[tuple[str, ...] | None, tyro.conf.arg(metavar="VIEW ...")] = None
    """the store's views to export (None: all)"""
    overwrite: bool = False
    """replace an existing --out"""


SUBCOMMANDS: dict[str, type] = {"import-lerobot": ImportLerobot, "export-lerobot": ExportLerobot}


def views_map(items: tuple[str, ...] | None) -> dict[str, str] | None:
    """``("left=cam_high", "wrist")`` -> ``{"left": "cam_high", "wrist": "wrist"}`` (the reader resolves keys)."""
    if not items:
        return None
    return dict(item.split("=", 1) if "=" in item else (item, item) for item in items)


def _frames(store) -> int:
    """Frames in every episode of ``store`` (memory-mapped: nothing is read but the small arrays)."""
    return sum(store.load(e, mmap=True, validate=False).length for e in store.episode_ids())


class _Selection:
    """episode_index values as ranges and single indices (``episode_selection``); supports ``in``."""

    def __init__(self, ranges: list[tuple[int, float]]):
        self.ranges = ranges

    def __contains__(self, i: int) -> bool:
        return any(a <= i < b for a, b in self.ranges)

    def missing(self, have: set[int]) -> list[int]:
        """The indices asked for by name (a single index, or a range closed at both ends) that ``have`` lacks:
        ``0:3`` with episode 1 missing imported two without a word. An open end (``20:``) asks for what there is."""
        return sorted({i for a, b in self.ranges if b != float("inf") for i in range(a, int(b))} - have)


def episode_selection(spec: tuple[str, ...] | None) -> _Selection | None:
    """``--episodes`` as a container of episode_index values; a malformed entry is a one-line UserError."""
    if spec is None:
        return None
    ranges = []
    for s in spec:
        try:
            if ":" in s:
                a, b = s.split(":")
                ranges.append((int(a) if a else 0, int(b) if b else float("inf")))
            else:
                ranges.append((int(s), int(s) + 1))
        except ValueError:
            raise UserError(f"--episodes {s!r}: expected A:B (either end may be left out) or an episode index, e.g. "
                            "0:20 or 20: or 3") from None
        a, b = ranges[-1]
        if a < 0 or b <= a:  # an empty or negative range selects nothing: said here, not as an empty store
            raise UserError(f"--episodes {s!r}: selects no episode (episode_index counts from 0; A:B needs A < B)")
    return _Selection(ranges)


def _import(a: ImportLerobot) -> int:
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.data.lerobot_import import import_lerobot

    s = import_lerobot(a.data, a.out, views=views_map(a.views), wrist_views=list(a.wrist) if a.wrist else None,
                       fps=a.fps, image_size=a.image_size, action_key=a.action_key, pose_key=a.pose_key,
                       allow_missing_pose=a.allow_missing_pose, progress=True, action_space=a.action_space,
                       action_names=list(a.action_names) if a.action_names else None,
                       action_targets=list(a.action_targets) if a.action_targets else None,
                       episodes=episode_selection(a.episodes), id_prefix=a.id_prefix,
                       **({} if a.state_key == "auto" else {"state_key": None if a.state_key == "none" else a.state_key}))
    store = EpisodeStore(s["out"])
    print(f"imported {s['written']} episodes ({s['skipped']} already there) from {a.data}; {s['out']} now holds "
          f"{len(store)} episodes, {_frames(store)} frames of views {', '.join(store.views)} at {s['fps']} fps, "
          f"{store.image_size[0]}x{store.image_size[1]}, actions {store.action_space.kind} {store.action_dim}-D")
    if s["too_short"]:
        print(f"skipped {len(s['too_short'])} episodes of fewer than 2 frames (LeRobot episode_index "
              f"{', '.join(map(str, s['too_short'][:10]))}{' ...' if len(s['too_short']) > 10 else ''})")
    print(f"train on it: sc3 train --config NAME --data {s['out']}")
    return 0


def _export(a: ExportLerobot) -> int:
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.data.lerobot_write import export_store

    from sc3_jax.core.validate import in_range, out_dir

    if a.crf is not None:  # h264's scale is 0-51, av1's 0-63: ffmpeg's own error would come after the first frames
        in_range("--crf", a.crf, 0, 51 if a.codec == "h264" else 63, f"{a.codec} quality, lower is better")
    out_dir(a.out, "--out")
    store = EpisodeStore(a.data)
    s = export_store(store, a.out, version=a.version, codec=a.codec, image_dtype=a.images, crf=a.crf,
                     views=list(a.views) if a.views else None, overwrite=a.overwrite)
    how = f"{a.codec} mp4s" if a.images == "video" else "PNGs in parquet"
    print(f"exported {s['episodes']} episodes, {s['frames']} frames, {s['tasks']} distinct task prompts from {a.data} "
          f"-> {s['out']} (LeRobot {a.version}, {how}): views {', '.join(a.views or store.views)} as observation.images.VIEW, "
          f"actions ({store.action_space.kind} {store.action_dim}-D) as action, "
          + ("state as observation.state" + (", ee_pose as observation.ee_pose" if store.has_pose else "")
             if store.state_dim else "ee_pose as observation.state"))
    return 0


_RUN = {"import-lerobot": _import, "export-lerobot": _export}


def main(argv: list[str]) -> int:
    try:
        return run_group("data", "LeRobot datasets <-> our episode store (docs/lerobot.md).", SUBCOMMANDS, _RUN, argv)
    except ModuleNotFoundError as err:  # the LeRobot extras (pyarrow, av) are optional
        raise UserError(f"{err}: install the LeRobot extras (pip install -e '.[lerobot]')") from err
    except (ValueError, RuntimeError) as err:  # a dataset or store we cannot convert as asked: LeRobotError & co
        if isinstance(err, UserError):
            raise
        raise UserError(" ".join(str(err).split())) from err
