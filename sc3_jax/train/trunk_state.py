"""A run's travelling state: everything a new machine needs to go on with a run as if it had never stopped.

An exported world model (``checkpoint.save``: config, norm stats, params, tokenizer), plus, in the same directory
and written in the same atomic step:

    trunk_state.npz   the optimizer's state, leaf by leaf (moments as bfloat16 by default: half the bytes, and a
                      moment's rounding moves the next updates by ~0.4% of themselves), the rng
    trunk.json        the step, the data iterator's position, the sha256 of params.npz (a later export into the same
                      directory that left an older trunk_state.npz behind is refused, not mixed)
    lineage.json      the model's compute since its initialisation (``lineage.py``)

Params stay float32 (the master weights), so a run resumed from here (``train.resume_from``) draws the same windows
and its losses match the unbroken run's to float tolerance (exactly, with float32 moments).
"""
from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import jax
import ml_dtypes
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.config import Config
from sc3_jax.core.errors import UserError

STATE_FILE, META_FILE = "trunk_state.npz", "trunk.json"
MOMENTS_DTYPES = {"float32": np.float32, "bfloat16": ml_dtypes.bfloat16}


def write(out: str | Path, cfg: Config, stats, state, data_state: dict, lineage: dict,
          moments: str = "bfloat16", head: str | Path | None = None) -> Path:
    """``state`` ({params, opt_state, step, rng}) and the data position at ``out``, a world model that can also be
    trained on. ``moments``: the dtype the optimizer's float leaves are stored in; ``head``: the run's
    state_head.npz, where it has one."""
    from sc3_jax.model import checkpoint

    if moments not in MOMENTS_DTYPES:
        raise UserError(f"moments dtype {moments!r}: expected one of {', '.join(MOMENTS_DTYPES)}")
    host = jax.device_get(state)
    arrays = {"rng": np.asarray(host["rng"])}
    for i, leaf in enumerate(jax.tree.leaves(host["opt_state"])):
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and leaf.ndim > 0:
            # bfloat16 has no npz type of its own: its bits, as uint16, tagged by the key
            arrays[f"opt/{i}/{moments}"] = leaf.astype(MOMENTS_DTYPES[moments]).view(
                np.uint16 if moments == "bfloat16" else np.float32)
        else:
            arrays[f"opt/{i}"] = leaf
    meta = {"step": int(host["step"]), "data": data_state, "moments": moments}

    def extra(tmp: Path):
        if head is not None and Path(head).is_file():  # the learned robot state travels with the model
            shutil.copyfile(head, tmp / "state_head.npz")
        atomic.save_npz(tmp / STATE_FILE, **arrays)
        meta["params_sha256"] = _sha256(tmp / "params.npz")
        atomic.write_json(tmp / META_FILE, meta)
        atomic.write_json(tmp / "lineage.json", lineage)

    return checkpoint.save(out, cfg, stats, host["params"], dtype=np.float32, extra=extra)


def is_state(path: str | Path) -> bool:
    return (Path(path) / META_FILE).is_file() and (Path(path) / STATE_FILE).is_file()


def read_meta(path: str | Path) -> dict:
    path = Path(path)
    if not is_state(path):
        raise UserError(f"{path}: not a run's travelling state (no {META_FILE} and {STATE_FILE}); make one with "
                        "`scripts/trunk.sh save` or `sc3 branch`")
    meta = atomic.read_json(path / META_FILE, "export the state again")
    if not isinstance(meta, dict) or not isinstance(meta.get("step"), int) or "data" not in meta:
        raise UserError(f"{path}/{META_FILE}: expected {{step, data, moments, params_sha256}}; export the state again")
    if meta.get("params_sha256") != _sha256(path / "params.npz"):
        raise UserError(f"{path}: params.npz is not the one {STATE_FILE} was saved with (the model was exported "
                        "again over it); export the state again")
    return meta


def read(path: str | Path, cfg: Config, abstract, shardings) -> tuple[dict, dict]:
    """(state, data_state) saved at ``path``, placed with ``shardings`` and cast back to the dtypes of ``abstract``
    (the state's shapes and shardings: ``train.state_shardings``)."""
    from sc3_jax.model import checkpoint

    path = Path(path)
    meta = read_meta(path)
    params = checkpoint.load_params(path, cfg, shardings=shardings["params"])
    with atomic.open_npz(path / STATE_FILE, "export the state again") as z:
        files = {k: z[k] for k in z.files}
    want = jax.tree.leaves(abstract["opt_state"])
    got = []
    for i, a in enumerate(want):
        key = next((k for k in (f"opt/{i}", f"opt/{i}/bfloat16", f"opt/{i}/float32") if k in files), None)
        if key is None:
            raise UserError(f"{path}/{STATE_FILE}: no optimizer leaf {i} of this config's {len(want)}; the state is "
                            "of another optimizer or model")
        v = files[key].view(ml_dtypes.bfloat16) if key.endswith("bfloat16") else files[key]
        if v.shape != a.shape:
            raise UserError(f"{path}/{STATE_FILE}: optimizer leaf {i} has shape {v.shape}, this config's model "
                            f"{a.shape}; the state is of another model")
        got.append(v.astype(a.dtype))
    opt_state = jax.tree.unflatten(jax.tree.structure(abstract["opt_state"]), got)
    host = {"opt_state": opt_state, "step": np.asarray(meta["step"], abstract["step"].dtype),
            "rng": np.asarray(files["rng"], abstract["rng"].dtype)}
    placed = {k: jax.tree.map(lambda x, s: jax.device_put(x, s), v, shardings[k]) for k, v in host.items()}
    placed["params"] = params
    return placed, meta["data"]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()

