"""Files written whole or not at all, and read back with one-line errors.

Every writer here writes a temporary file in the target's directory (same filesystem, so the rename is atomic),
fsyncs it and renames it over the target: a kill, a full disk or an exception leaves the old file (or none), never a
half-written one. ``read_json`` / ``open_npz`` turn a damaged file into a ``UserError`` naming it.
"""
from __future__ import annotations

import contextlib
import json
import os
import uuid
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from sc3_jax.errors import UserError


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` for the block to write; renamed over ``path`` when the block ends, removed if
    it raises. The temporary name keeps ``path``'s suffix (``np.save`` / ``np.savez`` would otherwise add theirs)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # not mkstemp: its 0600 mode would become the target's (the writer creates the file, under the umask)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())  # the data is on disk before the rename makes it the file
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    with contextlib.suppress(OSError):  # the rename itself survives a power loss (not possible everywhere)
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with replacing(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode())


def write_json(path: str | os.PathLike, obj, indent: int | None = 1) -> None:
    write_text(path, json.dumps(obj, indent=indent))


def save_npz(path: str | os.PathLike, compressed: bool = True, **arrays) -> None:
    with replacing(path) as tmp:
        (np.savez_compressed if compressed else np.savez)(tmp, **arrays)


def save_npy(path: str | os.PathLike, array) -> None:
    with replacing(path) as tmp:
        np.save(tmp, array)


def read_json(path: str | os.PathLike, fix: str = "restore it or delete it"):
    """The JSON in ``path``; a damaged file is a one-line ``UserError`` (file:line: problem; ``fix``)."""
    path = Path(path)
    try:
        return json.loads(path.read_bytes())
    except json.JSONDecodeError as e:
        raise UserError(f"{path}:{e.lineno}: not valid JSON ({e.msg}); {fix}") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text); {fix}") from None


@contextlib.contextmanager
def open_npz(path: str | os.PathLike, fix: str = "restore it or write it again"):
    """``np.load(path)`` as a context manager; a truncated or damaged archive (on opening or reading an array) is a
    one-line ``UserError`` naming the file, not numpy's zip or pickle errors."""
    def damaged():
        return UserError(f"{path}: damaged or truncated (not a readable .npz); {fix}")
    try:
        # a file cut short of the zip magic reaches numpy's pickle branch: ValueError about allow_pickle
        z = np.load(path)
    except (zipfile.BadZipFile, EOFError, ValueError):
        raise damaged() from None
    with z:
        try:
            yield z
        except (zipfile.BadZipFile, zlib.error, EOFError):
            raise damaged() from None
