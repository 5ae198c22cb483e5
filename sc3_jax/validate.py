"""Checks at the door, shared by the readers of every file kind (``data/episodes.py``, ``evaluate/results.py``,
``evaluate/labels.py``, ``checkpoint.py``, ``data/lerobot.py``) and by the commands' numeric options: each raises
one ``UserError`` line naming the file (the episode or record) and the fix, so that everything downstream may trust
what it is handed. docs/untrusted_inputs.md lists the faults and what each ends in."""
from __future__ import annotations

import math
import os
import pickle
import re

import numpy as np

from sc3_jax.errors import UserError

NUMERIC = "fiu"  # dtype kinds an array of numbers may have (bool, complex, strings, objects are not numbers)


def load_npy(path: str | os.PathLike, fix: str, mmap: bool = False) -> np.ndarray:
    """``np.load`` of one ``.npy``: a file cut short, a damaged header or a pickle is one line, never a traceback
    from inside numpy (``mmap length is greater than file size``)."""
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError, pickle.UnpicklingError) as e:
        if isinstance(e, OSError) and e.errno is not None:
            raise  # a file that cannot be opened: the command layer says so
        raise UserError(f"{path}: not a whole .npy array ({first_line(e)}); {fix}") from None


def numeric(x: np.ndarray, where: str, fix: str) -> np.ndarray:
    """``x`` if it holds real numbers (any int or float dtype), else one line: a retyped array (strings, bool,
    complex) would fail later as a TypeError from inside numpy or JAX."""
    if x.dtype.kind not in NUMERIC:
        raise UserError(f"{where}: holds {x.dtype} values, expected numbers; {fix}")
    return x


def json_object(obj, where: str, fix: str) -> dict:
    """``obj`` if it is a JSON object (a dict), else one line (a list or a number where a file needs fields)."""
    if not isinstance(obj, dict):
        raise UserError(f"{where}: expected a JSON object, got {type(obj).__name__}; {fix}")
    return obj


def is_count(x, most: int = 10**9) -> bool:
    """A positive integer no larger than ``most`` (JSON ``true`` is not one)."""
    return isinstance(x, int) and not isinstance(x, bool) and 0 < x <= most


def is_finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def in_range(name: str, value, low, high, why: str) -> None:
    """A numeric option within [low, high] (and finite), else one line naming the option and why the bound."""
    if not is_finite_number(value) or not low <= value <= high:
        raise UserError(f"{name} {value}: expected a number from {low:g} to {high:g} ({why})")


def same_files(paths) -> dict[tuple[int, int], list[str]]:
    """{(device, inode): [the spellings given]} of ``paths``: one file given as a relative and as an absolute path
    (or through a link) is one key, so a duplicate is found by what the file is, not by how it is spelt."""
    out: dict[tuple[int, int], list[str]] = {}
    for p in paths:
        st = os.stat(p)
        out.setdefault((st.st_dev, st.st_ino), []).append(str(p))
    return out


def host_available_bytes() -> float | None:
    """The machine's available memory (``MemAvailable`` of /proc/meminfo; None where there is none): what the data
    pipeline's host-side batches come out of, whatever the devices have."""
    try:
        with open("/proc/meminfo") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError):
        return None


def host_batch_bytes(cfg) -> int:
    """Host memory the training data pipeline holds for ``cfg`` (a training Config): its uint8 frame batches, one
    being assembled and those its read threads prefetch (``pipeline.make_iterator``)."""
    h, w = cfg.data.image_size
    frames = cfg.data.context_frames + cfg.data.future_frames + int(cfg.data.anchor)
    in_flight = 2 + 2 * int(cfg.data.read_threads)
    return len(cfg.data.views) * frames * int(h) * int(w) * 3 * int(cfg.data.batch_size) * in_flight


def check_host_memory(cfg, device_bytes: float = 0.0) -> None:
    """Refuse, in one line and before anything is written, a training batch whose host-side copies (plus
    ``device_bytes``: the train step's own estimate where the devices are this machine's CPUs, whose memory is the
    host's) cannot fit the machine's available memory: the kernel would otherwise kill the run without a word."""
    avail = host_available_bytes()
    if avail is None:
        return
    need = host_batch_bytes(cfg) + device_bytes
    if need > avail:
        most = max(1, int(cfg.data.batch_size * avail / need))
        raise UserError(f"--batch {cfg.data.batch_size}: its host-side batches need about {need / 1e9:.1f} "
                        f"GB, this machine has {avail / 1e9:.1f} GB available; lower it (at most about {most} here) "
                        "or --data.image-size")


def first_line(e: BaseException) -> str:
    """An exception's first line, spaces collapsed, at most 200 characters: what a one-line error quotes of it."""
    return " ".join((str(e).strip().splitlines() or [type(e).__name__])[0].split())[:200]


def taus(values) -> None:
    """Early-termination thresholds: each a non-negative number (inf: never stop), else one line."""
    for t in values or ():
        if math.isnan(t) or t < 0:
            raise UserError(f"--taus {t}: a threshold is a non-negative number (inf: never stop)")


def mask_paths(text: str) -> str:
    """``text`` with every path in it replaced by ``<path>``, by rule: a word starting with ``/``, ``~``, ``./`` or
    ``../``, or holding a ``/`` and ending in a file suffix (``sc3_jax/x.py``). A key such as ``observation/image``
    is not a path and stays."""
    word = r"[^\s'\"`,;()\[\]{}<>]+"
    rooted = rf"(?<![\w./])(?:~|\.\.?)?/(?!/){word}"  # not the // of a URL
    relative = r"(?<![\w/.~-])[\w.-]+(?:/[\w.-]+)*/[\w-]+\.[A-Za-z]\w{0,5}\b"
    return re.sub(rf"{rooted}|{relative}", "<path>", text)
