"""Checks at the door, shared by the readers of every file kind (``data/episodes.py``, ``evaluation/results.py``,
``evaluation/labels.py``, ``checkpoint.py``, ``data/lerobot.py``) and by the commands' numeric options: each raises
one ``UserError`` line naming the file (the episode or record) and the fix, so that everything downstream may trust
what it is handed. docs/untrusted_inputs.md lists the faults and what each ends in."""
from __future__ import annotations

import dataclasses
import math
import os
import pickle
import re
import stat
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError

NUMERIC = "fiu"  # dtype kinds an array of numbers may have (bool, complex, strings, objects are not numbers)


def regular_file(path: str | os.PathLike, fix: str, inside: str | os.PathLike | None = None) -> Path:
    """``path`` if it is a regular file (and, with ``inside``, one whose real path lies inside that directory's),
    else one line: a FIFO in place of an array would block its reader forever, a device would be read without end,
    and a file linked out of a store someone handed over is another store's (or the system's) data."""
    path = Path(path)
    try:
        st = os.stat(path)  # stat does not open: a FIFO is seen, not waited on
    except FileNotFoundError:
        raise UserError(f"{path}: missing (a link to nothing, or deleted); {fix}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UserError(f"{path}: not a regular file (a FIFO, device or directory); {fix}")
    if inside is not None:
        base = os.path.realpath(inside)
        if os.path.commonpath([base, os.path.realpath(path)]) != base:
            raise UserError(f"{path}: a link to a file outside {inside}; the store's files must be its own: {fix}")
    return path


def npy_fits(path: str | os.PathLike, fix: str) -> None:
    """One line when an ``.npy``'s header declares more data than the file holds (a header claiming 1e11 rows
    would have numpy ask for terabytes before reading a byte), read from the header alone; a header numpy cannot
    parse is left to ``np.load``, which says so."""
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            shape, _, dtype = readers[version](f)
        except (ValueError, KeyError, EOFError, OSError, SyntaxError, TypeError):
            return
        if dtype.hasobject:
            return  # a pickle: np.load refuses it (allow_pickle=False)
        need = f.tell() + math.prod(shape) * dtype.itemsize
    have = os.path.getsize(path)
    if need > have:
        raise UserError(f"{path}: its header declares {dtype} {list(shape)} ({need:,} bytes), the file holds "
                        f"{have:,}: damaged or crafted; {fix}")


def load_npy(path: str | os.PathLike, fix: str, mmap: bool = False, inside: str | os.PathLike | None = None
             ) -> np.ndarray:
    """``np.load`` of one ``.npy``: a file cut short, a damaged header or a pickle is one line, never a traceback
    from inside numpy (``mmap length is greater than file size``); so is anything but a regular file (inside
    ``inside`` where given: :func:`regular_file`) and a header declaring more than the file holds
    (:func:`npy_fits`), both found before anything is allocated."""
    regular_file(path, fix, inside)
    npy_fits(path, fix)
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
        show = lambda x: str(x) if isinstance(x, int) else f"{x:g}"  # noqa: E731  (2**32 - 1 in full, not 4.29e+09)
        raise UserError(f"{name} {value}: expected a number from {show(low)} to {show(high)} ({why})")


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


def out_dir(path: str | os.PathLike, option: str, links: bool = False) -> Path:
    """An output directory a command may create or write into, checked before its work: one line when it is a file,
    or under one (the work would end in NotADirectoryError, hours later), or a symbolic link (nothing is written
    through it into what it points at: a report/ linked out of a store someone handed over, a --out linked to
    another run's files). ``links=True``: a link is followed (a directory above it may be one either way)."""
    path = Path(path)
    if not links and path.is_symlink():
        raise UserError(f"{option} {path}: a symbolic link (to {os.readlink(path)}); nothing is written through it: "
                        "remove the link, or give another directory")
    for p in (path, *path.parents):
        if p.is_dir():
            break
        if os.path.lexists(p):
            what = "is a file" if p == path else f"is under {p}, a file"
            raise UserError(f"{option} {path}: {what}, not a directory: give a directory")
    return path


# sc3 train's numeric config fields: (section, field) -> (option, low, high, what); None values are the config's own
# "unset" (sized or derived later). A value outside is one line before anything is read or written: --batch 0 was a
# ZeroDivisionError inside JAX, --train.steps 0 an exit 0 with no checkpoint, --train.lr nan a NaN model
TRAIN_BOUNDS = {
    ("data", "batch_size"): ("--batch", 1, 1_000_000, "samples per step"),
    ("data", "context_frames"): ("--data.context-frames", 1, 1024, "frames"),
    ("data", "future_frames"): ("--data.future-frames", 1, 1024, "frames"),
    ("data", "pseudo_action_prob"): ("--data.pseudo-action-prob", 0, 1, "a probability"),
    ("data", "read_threads"): ("--data.read-threads", 0, 256, "threads"),
    ("data", "seed"): ("--data.seed", 0, 2**32 - 1, "a seed"),
    ("train", "steps"): ("--train.steps", 1, 10**9, "optimizer steps"),
    ("train", "lr"): ("--train.lr", 1e-12, 10, "a learning rate"),
    ("train", "warmup_steps"): ("--train.warmup-steps", 0, 10**9, "optimizer steps"),
    ("train", "weight_decay"): ("--train.weight-decay", 0, 10, "AdamW's decay"),
    ("train", "b1"): ("--train.b1", 0, 0.999999, "Adam's first-moment decay, below 1"),
    ("train", "b2"): ("--train.b2", 0, 0.999999, "Adam's second-moment decay, below 1"),
    ("train", "grad_clip"): ("--train.grad-clip", 1e-12, 1e12, "a gradient norm; 0 would never move the model"),
    ("train", "grad_accum"): ("--train.grad-accum", 1, 1 << 20, "micro-batches per step"),
    ("train", "seed"): ("--train.seed", 0, 2**32 - 1, "a seed"),
    ("train", "log_every"): ("--train.log-every", 1, 10**9, "steps"),
    ("train", "ckpt_every"): ("--train.ckpt-every", 1, 10**9, "steps"),
    ("train", "keep_checkpoints"): ("--train.keep-checkpoints", 1, 10**6, "checkpoints"),
    ("flow", "t_logit_mean"): ("--flow.t-logit-mean", -100, 100, "a logit"),
    ("flow", "t_logit_std"): ("--flow.t-logit-std", 1e-6, 100, "a spread"),
    ("flow", "video_loss_weight"): ("--flow.video-loss-weight", 0, 1e6, "a loss weight"),
    ("flow", "action_loss_weight"): ("--flow.action-loss-weight", 0, 1e6, "a loss weight"),
    ("flow", "context_noise_max"): ("--flow.context-noise-max", 0, 1, "a noise level"),
    ("flow", "distill_steps"): ("--flow.distill-steps", 1, 1000, "sampler steps"),
}


def train_config(cfg) -> None:
    """``sc3 train``'s config at the door (``TRAIN_BOUNDS``, the mode probabilities, the strides, the mesh, the
    workdir), one ``UserError`` line for the first field out of bounds, before anything is read or written."""
    for (section, field), (option, low, high, what) in TRAIN_BOUNDS.items():
        value = getattr(getattr(cfg, section), field)
        if value is not None:
            in_range(option, value, low, high, what)
    probs = tuple(cfg.modes.probs)
    for p in probs:
        in_range("--modes.probs", p, 0, 1, "probabilities")
    if not sum(probs) > 0:
        raise UserError(f"--modes.probs {' '.join(map(str, probs))}: all zero, no training mode is drawn")
    if not cfg.data.strides:
        raise UserError("--data.strides: give at least one frame stride")
    for s in cfg.data.strides:
        in_range("--data.strides", s, 1, 1000, "frame strides")
    for axis in ("fsdp", "tensor", "context"):
        in_range(f"--mesh.{axis}", getattr(cfg.mesh, axis), 1, 1 << 16, "devices")
    if cfg.mesh.data != -1:
        in_range("--mesh.data", cfg.mesh.data, 1, 1 << 16, "devices; -1: all the others")
    out_dir(cfg.train.workdir, "--train.workdir")


def check_config_types(cfg, default, where: str, fix: str, prefix: str = "") -> None:
    """Every field of a config read from a file has its default's type (``model.dim: "abc"`` would otherwise be a
    TypeError from inside JAX): one line naming the field. A field whose default is None has its annotation's type
    or is null. ``cfg``: the config, or the file's raw dict (fields absent keep their defaults; lists as tuples),
    which names the field whose type made building the config fail."""
    raw = isinstance(cfg, dict)
    for f in dataclasses.fields(default):
        if raw and f.name not in cfg:
            continue
        have, want, name = cfg[f.name] if raw else getattr(cfg, f.name), getattr(default, f.name), prefix + f.name
        if raw and isinstance(have, list) and isinstance(want, tuple):
            have = tuple(have)
        if dataclasses.is_dataclass(want):
            if not (isinstance(have, dict) if raw else dataclasses.is_dataclass(have)):
                raise UserError(f"{where}: {name} is {have!r}, expected a section of fields; {fix}")
            check_config_types(have, want, where, fix, name + ".")
            continue
        ok = {bool: lambda v: isinstance(v, bool), str: lambda v: isinstance(v, str),
              int: lambda v: isinstance(v, int) and not isinstance(v, bool),
              float: lambda v: is_finite_number(v) or v in (math.inf, -math.inf),
              tuple: lambda v: isinstance(v, tuple)}.get(type(want))
        if want is not None and ok is not None and not ok(have):
            raise UserError(f"{where}: {name} is {have!r}, expected {type(want).__name__}; {fix}")
        kind = str(f.type).removesuffix(" | None")
        if want is None and have is not None and kind in _ENTRY and not _ENTRY[kind](have):  # an optional field,
            raise UserError(f"{where}: {name} is {have!r}, expected {kind} or null; {fix}")  # set: of its type
        if isinstance(want, tuple):  # and its entries: ["a", "b"] as data.image_size was a TypeError in JAX
            _check_entries(have, str(f.type), f"{where}: {name} is {list(have)!r}", fix)


_ENTRY = {"int": lambda v: isinstance(v, int) and not isinstance(v, bool), "str": lambda v: isinstance(v, str),
          "float": lambda v: is_finite_number(v) or v in (math.inf, -math.inf)}


def _check_entries(have: tuple, annotation: str, said: str, fix: str) -> None:
    """A tuple field's entries against its annotation: ``tuple[int, int]`` two ints, ``tuple[str, ...]`` any number
    of strings (another annotation: unchecked)."""
    if not annotation.startswith("tuple[") or not annotation.endswith("]"):
        return
    kinds = [k.strip() for k in annotation[len("tuple["):-1].split(",")]
    if not all(k in _ENTRY or k == "..." for k in kinds):
        return
    many = kinds[-1] == "..."
    if not many and len(have) != len(kinds):
        raise UserError(f"{said}, expected {len(kinds)} entries ({', '.join(kinds)}); {fix}")
    for v, k in zip(have, [kinds[0]] * len(have) if many else kinds):
        if not _ENTRY[k](v):
            raise UserError(f"{said}, expected {kinds[0] + ' entries' if many else ', '.join(kinds)}; {fix}")
