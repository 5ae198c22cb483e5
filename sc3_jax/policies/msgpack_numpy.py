"""msgpack with numpy arrays and scalars, wire-compatible with openpi's ``openpi_client.msgpack_numpy``.

Encoding (the openpi convention; keys are *bytes*):
    np.ndarray -> {b"__ndarray__": True, b"data": arr.tobytes() (C order), b"dtype": dtype.str, b"shape": shape}
    np.generic -> {b"__npgeneric__": True, b"data": scalar.item(), b"dtype": dtype.str}
Object ("O"), void/structured ("V") and complex ("c") dtypes are refused (openpi refuses the same set: nothing on
the wire ever falls back to pickle). Datetime/timedelta ("M"/"m") are refused too because their ``.item()`` is not a
msgpack type; openpi would fail on them later with a less useful error.

Decoding returns *writable* arrays (a copy of the received buffer) so callers may modify them in place; openpi returns
read-only views of the message buffer, which is otherwise identical. Everything else (dicts, lists, str, bytes, ints,
floats, bools, None) is plain msgpack; tuples come back as lists and string dict keys come back as ``str``.
Unlike openpi's packer we pack with ``strict_types=True`` so that ``np.float64`` and ``np.str_`` scalars (subclasses
of ``float`` / ``str``) keep their numpy type on the wire; the bytes are still decodable by openpi's unpacker.
"""
from __future__ import annotations

import functools
from typing import Any

import msgpack
import numpy as np

__all__ = ["pack_array", "unpack_array", "packb", "unpackb", "Packer", "Unpacker", "REFUSED_KINDS"]

REFUSED_KINDS = {"O": "object", "V": "void/structured", "c": "complex", "M": "datetime64", "m": "timedelta64"}


def _check_dtype(obj: np.ndarray | np.generic) -> None:
    kind = obj.dtype.kind
    if kind in REFUSED_KINDS:
        raise TypeError(
            f"cannot send a numpy {'array' if isinstance(obj, np.ndarray) else 'scalar'} of dtype {obj.dtype!r} "
            f"({REFUSED_KINDS[kind]}) over the openpi msgpack protocol: object, void, complex and datetime dtypes "
            f"are refused; convert it to a plain numeric, bool or string dtype first"
        )


def pack_array(obj: Any) -> Any:
    """msgpack ``default`` hook: numpy arrays / scalars -> openpi's tagged dicts."""
    if isinstance(obj, (np.ndarray, np.generic)):
        _check_dtype(obj)
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    # The packer runs with strict_types=True (so that np.float64 / np.str_, which subclass float / str, keep their
    # numpy dtype instead of silently becoming Python scalars): plain containers and subclasses of builtins come here.
    if isinstance(obj, (tuple, list)):
        return list(obj)
    if isinstance(obj, dict):
        return dict(obj)
    for base in (bool, int, float, str, bytes):
        if isinstance(obj, base):
            return base(obj)
    # jax arrays and anything else array-like that msgpack cannot encode: go through numpy once.
    if hasattr(obj, "__array__") and hasattr(obj, "dtype") and hasattr(obj, "shape"):
        return pack_array(np.asarray(obj))
    raise TypeError(f"cannot serialize {type(obj).__name__!r} object with the openpi msgpack protocol")


def unpack_array(obj: dict) -> Any:
    """msgpack ``object_hook``: openpi's tagged dicts -> numpy arrays / scalars."""
    if b"__ndarray__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in REFUSED_KINDS:
            raise TypeError(f"refusing to decode an array of dtype {dtype!r} ({REFUSED_KINDS[dtype.kind]})")
        shape = tuple(obj[b"shape"])
        return np.frombuffer(obj[b"data"], dtype=dtype).reshape(shape).copy()
    if b"__npgeneric__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in REFUSED_KINDS:
            raise TypeError(f"refusing to decode a scalar of dtype {dtype!r} ({REFUSED_KINDS[dtype.kind]})")
        return dtype.type(obj[b"data"])
    return obj


Packer = functools.partial(msgpack.Packer, default=pack_array, strict_types=True)
packb = functools.partial(msgpack.packb, default=pack_array, strict_types=True)
Unpacker = functools.partial(msgpack.Unpacker, object_hook=unpack_array)
unpackb = functools.partial(msgpack.unpackb, object_hook=unpack_array)
