"""Files written whole or not at all, and read back with one-line errors.

Every writer here writes a temporary beside its target (same file system, so the rename is atomic), fsyncs it and
renames it over the target: a kill, a full disk or an exception leaves the old file (or none), never a half-written
one. :func:`replacing_dir` does the same for a directory written as one (an exported model), :func:`staged` for a set
of files written into a directory that holds other things too (a report). A directory that cannot be written (no
permission, read-only, full) is a ``UserError`` naming it; ``read_json`` / ``open_npz`` / ``read_jsonl`` turn a
damaged file into a ``UserError`` naming it (and the line).

A temporary's name says which process on which host wrote it (``.NAME.HOST-PID.XXXXXXXX.tmp[.SUFFIX]``), so that
:func:`remove_stale` can delete those a killed writer left, and no other.
"""
from __future__ import annotations

import contextlib
import ctypes
import errno
import gzip
import json
import os
import re
import shutil
import socket
import sys
import uuid
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError

# errors that mean "this place cannot be written", which the user fixes (another --out, free space), not a bug
_UNWRITABLE = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENOTDIR}
_HOST = socket.gethostname()


def _tmp_path(path: Path, suffix: str | None = None) -> Path:
    suffix = path.suffix if suffix is None else suffix
    stem = path.name[:len(path.name) - len(suffix)] if suffix else path.name
    return path.with_name(f".{stem}.{_HOST}-{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp{suffix}")


def temp_dir(path: str | os.PathLike) -> Path:
    """A new empty directory beside ``path``, named as a temporary of this process (so :func:`remove_stale` knows
    it), for writing ``path``'s contents before one rename. Not ``tempfile.mkdtemp``: its 0700 mode would become the
    target's; this one is made under the user's umask like any other directory."""
    tmp = _tmp_path(Path(path), suffix="")
    tmp.mkdir()
    return tmp


def _unwritable(path: Path, e: BaseException, fix: str = "choose another place (or free space there)"):
    """``e`` as a one-line ``UserError`` naming ``path`` if it says the place cannot be written, else None."""
    if isinstance(e, OSError) and e.errno in _UNWRITABLE:
        return UserError(f"{path}: cannot write there ({os.strerror(e.errno)}); {fix}")
    return None


def _raise_unwritable(path: Path, e: BaseException):
    """Inside ``except``: re-raise ``e``, as a one-line ``UserError`` where it says ``path`` cannot be written."""
    user = _unwritable(path, e)
    if user is None:
        raise e
    raise user from None


def _fsync(path: Path) -> None:
    with contextlib.suppress(OSError):  # not possible everywhere (a directory on some systems)
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` for the block to write; renamed over ``path`` when the block ends, removed if
    it raises. The temporary name keeps ``path``'s suffix (``np.save`` / ``np.savez`` would otherwise add theirs)."""
    path = Path(path)
    # not mkstemp: its 0600 mode would become the target's (the writer creates the file, under the umask)
    tmp = _tmp_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())  # the data is on disk before the rename makes it the file
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        _raise_unwritable(path, e)
    _fsync(path.parent)  # the rename itself survives a power loss


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # a C library without it
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):  # a kernel or file system without it
        return False
    raise OSError(err, os.strerror(err), str(b))


def _link_tree(src: Path, dst: Path) -> None:
    """``src`` (a file or a directory) at ``dst`` as hard links (copies where links are not possible)."""
    def link(s, d):
        try:
            os.link(s, d)
        except OSError:
            shutil.copy2(s, d)
    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, symlinks=True, copy_function=link)
    elif src.is_symlink():
        os.symlink(os.readlink(src), dst)
    else:
        link(src, dst)


@contextlib.contextmanager
def replacing_dir(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary directory beside ``path`` for the block to fill; when the block ends it takes ``path``'s place in
    one step, so a reader (or a kill) sees the old directory or the new one, never a mix of the two. Entries of an
    existing ``path`` that the block did not write are carried over (as hard links: files another tool put there,
    such as a model's ``diagnose.json``); the block's own replace theirs whole. Removed if the block raises."""
    path = Path(path)
    if path.is_symlink():  # replace what it points at, not the link
        path = path.resolve()
    tmp = _tmp_path(path, suffix="")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale(path.parent)
        tmp.mkdir()
        yield tmp
        if path.exists():
            for entry in path.iterdir():
                if not os.path.lexists(tmp / entry.name):
                    _link_tree(entry, tmp / entry.name)
        for f in (p for p in tmp.rglob("*") if p.is_file() and not p.is_symlink()):
            _fsync(f)
        if not path.exists():
            os.rename(tmp, path)
        elif _exchange(tmp, path):
            shutil.rmtree(tmp)  # the old directory, now under the temporary name
        else:  # two renames. A kill between them leaves the old directory as .NAME.HOST-PID.XXXXXXXX.old, which
            # remove_stale keeps (the new one, a .tmp, it deletes: a rerun writes it again)
            old = _tmp_path(path, suffix="").with_suffix(".old")
            os.rename(path, old)
            try:
                os.rename(tmp, path)
            except BaseException:
                os.rename(old, path)
                raise
            shutil.rmtree(old)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        _raise_unwritable(path, e)
    _fsync(path.parent)


@contextlib.contextmanager
def staged(directory: str | os.PathLike, last: tuple[str, ...] = ()) -> Iterator[Path]:
    """A temporary directory inside ``directory`` for the block to write files into; when the block ends each file
    is renamed into ``directory`` (the names in ``last`` after the others, in that order), replacing one of the same
    name whole. A block that raises (or a kill before the renames) changes nothing in ``directory``, and one this
    call created is removed again. For outputs that share their directory with other files (a report written into a
    results store), which :func:`replacing_dir` would have to take whole."""
    directory = Path(directory)
    created = [p for p in (directory, *directory.parents) if not p.exists()]
    stage = directory / _tmp_path(Path("stage"), suffix="").name
    try:
        directory.mkdir(parents=True, exist_ok=True)
        remove_stale(directory)
        stage.mkdir()
        yield stage
        names = sorted(os.listdir(stage), key=lambda n: last.index(n) + 1 if n in last else 0)
        for n in names:
            if (stage / n).is_dir():
                raise IsADirectoryError(f"{stage / n}: atomic.staged moves files only")
            _fsync(stage / n)
        for n in names:
            os.replace(stage / n, directory / n)
        _fsync(directory)
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        for p in created:  # deepest first; only what this call made, and only while empty
            with contextlib.suppress(OSError):
                p.rmdir()
        _raise_unwritable(directory, e)
    stage.rmdir()


def remove_stale(directory: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """Delete the temporaries in ``directory`` that a writer on this host left when it was killed (its process no
    longer runs); returns them. Those of running processes, or of other hosts sharing the file system, stay."""
    directory = Path(directory)
    pattern = re.compile(rf"\..+\.{re.escape(_HOST)}-(\d+)\.[0-9a-f]{{8}}\.tmp(\.[^.]*)?")
    found = []
    try:
        entries = list(directory.rglob(".*.tmp*") if recursive else directory.glob(".*.tmp*"))
    except OSError:
        return found
    for p in entries:
        m = pattern.fullmatch(p.name)
        if m and not _running(int(m[1])):
            found.append(p)
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
    return found


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


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
    _regular(path, fix)
    try:
        return json.loads(path.read_bytes())
    except json.JSONDecodeError as e:
        raise UserError(f"{path}:{e.lineno}: not valid JSON ({e.msg}); {fix}") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text); {fix}") from None


def read_jsonl(path: str | os.PathLike, what: str, fix: str) -> list:
    """The JSON objects of an append-only JSONL file, one per complete line. A last line without its newline (cut by
    a kill, or being written right now) is left out; a damaged complete line is a one-line ``UserError``:
    ``path:line: not WHAT (problem); FIX``. Reading never writes. A ``.gz`` file is read decompressed (an archived
    store's records)."""
    path = Path(path)
    if not path.exists():
        return []
    _regular(path, fix)
    raw = path.read_bytes()
    if path.suffix == ".gz":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as e:
            raise UserError(f"{path}: not a complete gzip file ({e}); {fix}") from None
    out = []
    for i, line in enumerate(raw[:raw.rfind(b"\n") + 1].split(b"\n"), 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            problem = None if isinstance(obj, dict) else "not a JSON object"
        except ValueError as e:  # JSON, or bytes that are not UTF-8
            problem = getattr(e, "msg", "not UTF-8 text")
        if problem:
            raise UserError(f"{path}:{i}: not {what} ({problem}); {fix}")
        out.append(obj)
    return out


def _regular(path: Path, fix: str) -> None:
    """An existing ``path`` that is not a regular file (a FIFO would block the read forever, a device never end it)
    is one line; a missing one is left to the caller (it may be optional)."""
    if path.exists() and not path.is_file():
        raise UserError(f"{path}: not a regular file (a FIFO, device or directory); {fix}")


def _npz_fits(z, path, fix: str) -> None:
    """Each array of an opened ``.npz`` declares no more data than its member holds (a header claiming 1e11 rows
    would have numpy allocate terabytes before reading), read from the headers alone."""
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    zf = getattr(z, "zip", None)
    for info in (zf.infolist() if zf is not None else ()):
        with zf.open(info) as f:
            try:
                version = np.lib.format.read_magic(f)
                shape, _, dtype = readers[version](f)
            except (ValueError, KeyError, EOFError, OSError, SyntaxError, TypeError):
                continue  # left to np.load, which says what is wrong
            header = f.tell()
        if not dtype.hasobject and header + int(np.prod(shape, dtype=object)) * dtype.itemsize > info.file_size:
            raise UserError(f"{path}: array {info.filename} declares {dtype} {list(shape)}, more than it holds "
                            f"({info.file_size:,} bytes): damaged or crafted; {fix}")


def drop_cut_line(path: str | os.PathLike) -> int:
    """Before appending to a JSONL file again: drop a last line cut by a kill (the next line would be glued to it),
    by writing the complete lines to a new file renamed over the old one, so a kill here loses nothing. Returns the
    bytes dropped (0: nothing to do)."""
    path = Path(path)
    if not path.exists():
        return 0
    raw = path.read_bytes()
    if not raw or raw.endswith(b"\n"):
        return 0
    keep = raw[:raw.rfind(b"\n") + 1]
    write_bytes(path, keep)
    return len(raw) - len(keep)


@contextlib.contextmanager
def open_npz(path: str | os.PathLike, fix: str = "restore it or write it again"):
    """``np.load(path)`` as a context manager; a truncated or damaged archive (on opening or reading an array) is a
    one-line ``UserError`` naming the file, not numpy's zip or pickle errors."""
    def damaged():
        return UserError(f"{path}: damaged or truncated (not a readable .npz); {fix}")
    _regular(Path(path), fix)
    try:
        # a file cut short of the zip magic reaches numpy's pickle branch: ValueError about allow_pickle
        z = np.load(path)
    except (zipfile.BadZipFile, EOFError, ValueError):
        raise damaged() from None
    with z:
        try:
            _npz_fits(z, path, fix)
            yield z
        except (zipfile.BadZipFile, zlib.error, EOFError):
            raise damaged() from None
        except ValueError as e:  # an object array is a pickle: never loaded (it could run code), said in one line
            if "allow_pickle" not in str(e):
                raise
            raise UserError(f"{path}: holds an object array (a pickle, never loaded here); {fix}") from None


def drop_rows_after(path: str | os.PathLike, step: int) -> int:
    """Rewrite the metrics log ``path`` without its rows of steps after ``step`` (atomically); returns how many were
    dropped. A line that does not read as a row is kept as it is (the log is informational: read_metrics names it)."""
    path = Path(path)
    if not path.is_file():
        return 0
    lines = path.read_text().splitlines(keepends=True)

    def after(line: str) -> bool:
        try:
            row = json.loads(line)
        except ValueError:
            return False
        return isinstance(row, dict) and isinstance(row.get("step"), int) and row["step"] > step
    keep = [line for line in lines if not after(line)]
    if len(keep) != len(lines):
        write_text(path, "".join(keep))
    return len(lines) - len(keep)
