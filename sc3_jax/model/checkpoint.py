"""A saved world model: its config, params, normalisation stats and (learned) tokenizer -- read, written, exported.

Three kinds of directory hold one, and every reader here takes any of them:

    a ``sc3 train`` workdir   config.json, norm_stats.json, checkpoints/<step>/state (orbax, the whole train state)
    an exported world model   config.json, norm_stats.json, params.npz (any float dtype, or int8 matrices with
                              per-output-channel scales), tokenizer/ (conv_ae)
    a ``sc3 convert`` output  config.json, params/ (orbax, params only)

:func:`load` gives (config, stats, params); :func:`save` / :func:`export` write the exported form (small enough to
commit, e.g. ``sc3_jax/benchmarks/bussing/shipped/bussing_sim``).

A saved model records its robot's facts, and :func:`read_robot` is the one reader of them (rollouts, sweeps,
diagnostics and plans take them from there, never from a default): the data's frame rate (config.json
``data.fps``) and recorded state size (``data.state_dim``), its views (``data.views``) -- all three filled from the
dataset's dataset.json by ``sc3 train`` (``data/shape.py``) -- and its action space, kind and dimension
(norm_stats.json ``action_space``). A model saved before config.json recorded fps / state_dim reads them from the
store it was trained on (``data.path``) where that is still there, else names the missing field.

Training's own checkpoints (optimizer state and data position, for resuming) are written by ``train.py``; this
module only reads their params.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp

from sc3_jax.core import atomic
from sc3_jax.core.config import Config, config_from_dict
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.core.errors import UserError
from sc3_jax.model import dit, saved_model
from sc3_jax.model.shapes import check_shapes
from sc3_jax.model.tokenizer import token_geometry
from sc3_jax.core.validate import check_config_types, first_line, is_finite_number, json_object, numeric


# ================================================================================================================
# Reading
# ================================================================================================================
def load(path: str | Path, step: int | None = None) -> tuple[Config, NormStats, dict]:
    """(config, norm stats, params) of a training workdir (latest orbax checkpoint, or ``step``) or an exported
    world model."""
    cfg = read_config(path)
    return cfg, read_norm_stats(path), load_params(path, cfg, step)


def read_config(path: str | Path, what: str = "") -> Config:
    """The config of a saved model; a tokenizer shipped inside the model directory is referred to by its absolute
    path. ``what``: a prefix for the error message."""
    path = Path(path)
    if not (path / "config.json").exists():
        raise FileNotFoundError(f"{what}{path}: no config.json (expected a `sc3 train` workdir, an exported world "
                                "model or a `sc3 convert` output)")
    fix = "restore it from a copy, or export the model again"
    raw = json_object(atomic.read_json(path / "config.json", fix), f"{path}/config.json", fix)
    try:
        cfg = config_from_dict(raw)
    except (TypeError, ValueError, AttributeError) as e:  # a section retyped (a list where fields are)
        check_config_types(raw, Config(), f"{path}/config.json", fix)  # the field whose type it was, named
        raise UserError(f"{path}/config.json: does not read as a config ({e}); {fix}") from None
    saved_model.check_config(cfg, f"{path}/config.json", fix)
    tp = cfg.model.tokenizer_path
    if tp and not Path(tp).is_absolute() and (path / tp).exists():  # a tokenizer shipped inside the model dir
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, tokenizer_path=str((path / tp).absolute())))
    # its tokenizer and statistics too, before anything is built from them (a damaged field was a JAX traceback)
    saved_model.check_tokenizer(cfg, f"{path}/config.json")
    saved_model.check_norm_stats(path, cfg)
    return cfg


@dataclasses.dataclass(frozen=True)
class Robot:
    """A saved world model's robot facts (:func:`read_robot`)."""

    fps: float  # the frame rate of the data it was trained on
    action_space: ActionSpace  # what its actions mean (kind, dimension)
    views: tuple[str, ...]  # its cameras, in the model's view order
    state_dim: int  # the size of the robot state its data records (0: none)

    @property
    def action_dim(self) -> int:
        return self.action_space.dim


MAX_FPS, MAX_STATE_DIM = 1000.0, 4096  # beyond any camera's rate and any robot's state: a damaged config.json


def read_robot(path: str | Path, cfg: Config | None = None) -> Robot:
    """The robot facts of the saved model at ``path`` (any kind :func:`load` reads; ``cfg``: its config as the caller
    runs it, where already read): config.json's ``data.fps`` / ``data.views`` / ``data.state_dim``, norm_stats.json's
    action space (a ``sc3 convert`` output, which has none: the model's dimension as absolute targets, naming no
    robot). A fact config.json predates is read from the store the model was trained on (:func:`training_store`),
    else a one-line UserError names the field to add; so is a frame rate ``cfg.rollout.control_hz`` does not divide
    (a rollout advances a whole number of the data's frames per model step)."""
    path = Path(path)
    cfg = read_config(path) if cfg is None else cfg
    robot = _recorded_robot(path, cfg)
    far = [i for i in robot.action_space.measured if i >= robot.state_dim > 0]
    if far:
        raise UserError(f"{path}/norm_stats.json: action_space.measured {list(robot.action_space.measured)} names "
                        f"state entries past the recorded state's {robot.state_dim}: restore it from the model it "
                        "came with")
    hz = cfg.rollout.control_hz
    stride = robot.fps / hz if is_finite_number(hz) and hz > 0 else 0.0
    if round(stride) < 1 or abs(stride - round(stride)) > 1e-6:
        raise UserError(f"{path}/config.json: data.fps {robot.fps:g} is not a whole multiple of rollout.control_hz "
                        f"{hz!r} (a rollout advances a whole number of the data's frames per model step): restore "
                        "data.fps (the episodes' frame rate), or set rollout.control_hz to a rate that divides it")
    return robot


def training_store(path: str | Path, cfg: Config) -> Path | None:
    """The episode store the saved model at ``path`` was trained on (config.json ``data.path``), where that can be
    known: an absolute path. A relative one was relative to wherever training ran, which nothing records, so it is
    never read against the current directory (whatever ``./train`` that holds is another store): None."""
    p = Path(cfg.data.path) if cfg.data.path else None
    return p if p is not None and p.is_absolute() else None


def _recorded_robot(path: Path, cfg: Config) -> Robot:
    """:func:`read_robot`'s facts, unchecked against the rollout's rate (what :func:`export` records)."""
    d = cfg.data
    if (path / "norm_stats.json").exists():
        space = read_norm_stats(path).action_space
    else:
        space = ActionSpace("absolute", cfg.model.action_dim)
    fps, state_dim = d.fps, d.state_dim
    if fps is not None and not (is_finite_number(fps) and 0 < fps <= MAX_FPS):
        raise UserError(f"{path}/config.json: data.fps is {fps!r}, expected the episodes' frame rate, a number in "
                        f"(0, {MAX_FPS:g}]: restore it")
    if state_dim is not None and not (isinstance(state_dim, int) and not isinstance(state_dim, bool)
                                      and 0 <= state_dim <= MAX_STATE_DIM):
        raise UserError(f"{path}/config.json: data.state_dim is {state_dim!r}, expected the robot state's size, an "
                        f"integer in [0, {MAX_STATE_DIM}]: restore it")
    if fps is None or state_dim is None:
        store = training_store(path, cfg)
        meta = store / "dataset.json" if store is not None else None
        info = atomic.read_json(meta, "restore it (the episode store's metadata)") if meta and meta.is_file() else None
        if fps is None:
            if not (isinstance(info, dict) and is_finite_number(info.get("fps")) and info["fps"] > 0):
                where = (f"its training data {d.path} is not here to read it from" if store is not None or not d.path
                         else f"its training data's path {d.path!r} is relative to wherever it was trained, so "
                              "it is not read")
                raise UserError(f"{path}/config.json: no data.fps (saved before models recorded their data's frame "
                                f"rate) and {where}: add \"fps\": N (the episodes' frame rate) to the \"data\" "
                                "section of config.json")
            fps = info["fps"]
        if state_dim is None:
            st = info.get("state") if isinstance(info, dict) else None
            state_dim = int(st["dim"]) if isinstance(st, dict) and isinstance(st.get("dim"), int) else 0
    return Robot(float(fps), space, tuple(d.views), int(state_dim))


def with_robot(cfg: Config, robot: Robot) -> Config:
    """``cfg`` with ``robot``'s frame rate and state size recorded (what :func:`save` writes to config.json)."""
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, fps=robot.fps, state_dim=robot.state_dim))


def read_norm_stats(path: str | Path) -> NormStats:
    path = Path(path) / "norm_stats.json"
    if not path.exists():
        raise FileNotFoundError(f"{path.parent}: no norm_stats.json (a `sc3 train` workdir or an exported world "
                                "model has one; a `sc3 convert` output does not)")
    return NormStats.load(path)


def param_shapes(cfg: Config) -> dict:
    """The params of ``cfg``'s model as ``jax.ShapeDtypeStruct`` (nothing allocated)."""
    token_dim, grid = token_geometry(cfg)
    return jax.eval_shape(lambda: dit.init_params(cfg.model, token_dim, jax.random.key(0), grid))


def load_params(path: str | Path, cfg: Config, step: int | None = None, shardings=None):
    """Params of a trained run (latest orbax checkpoint), an exported world model (``params.npz``, any float dtype)
    or a ``sc3 convert`` output (orbax ``params/``), as ``cfg``'s param dtype. ``shardings``: a params-shaped tree of
    shardings (default: all on the first device); every leaf is read straight into its shards, so a model larger
    than one device's memory loads onto a mesh (orbax reads only each device's slice; an npz leaf passes through
    host memory once). A run's optimizer state is not read."""
    path = Path(path)
    want = param_shapes(cfg)
    if shardings is None:
        one = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        shardings = jax.tree.map(lambda _: one, want)
    target = jax.tree.map(lambda w, s: jax.ShapeDtypeStruct(w.shape, w.dtype, sharding=s), want, shardings)
    if (path / "params.npz").exists():
        return _load_npz(path / "params.npz", target)
    item, in_state = _orbax_item(path, step)
    target = {"params": target} if in_state else target
    try:
        out = ocp.PyTreeCheckpointer().restore(item, args=ocp.args.PyTreeRestore(
            item=target, restore_args=ocp.checkpoint_utils.construct_restore_args(target), partial_restore=True))
    except Exception as e:  # noqa: BLE001  (tensorstore raises a bare Exception for a checkpoint cut short)
        raise UserError(f"{item}: not a whole checkpoint of this config's model ({first_line(e)}); restore it, or "
                        "give another --step / model") from None
    return out["params"] if in_state else out


def load_init_from(cfg: Config, shardings=None) -> dict:
    """Params that ``cfg.train.init_from`` names (any saved model), checked leaf by leaf against this config's
    shapes before anything is read, then loaded straight into ``shardings`` as this config's param dtype (their norm
    stats are picked up by ``train.prepare_data``)."""
    src = Path(cfg.train.init_from)
    read_config(src, what="init_from ")
    have = {jax.tree_util.keystr(k): v.shape for k, v in jax.tree_util.tree_flatten_with_path(param_shapes(cfg))[0]}
    check_shapes(have, source_shapes(src), f"init_from {src}: params do not fit this model config:")
    return load_params(src, cfg, shardings=shardings)


def source_shapes(path: str | Path, step: int | None = None) -> dict[str, tuple[int, ...]]:
    """``{keystr: shape}`` of the params that ``load_params`` would read, from metadata only (nothing loaded)."""
    path = Path(path)
    if (path / "params.npz").exists():
        out = {}
        with atomic.open_npz(path / "params.npz", NPZ_FIX) as z:
            for name in z.zip.namelist():
                if name.endswith(SCALE_SUFFIX + ".npy"):
                    continue
                with z.zip.open(name) as f:
                    version = np.lib.format.read_magic(f)
                    read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
                    shape = read[version](f)[0]
                out["".join(f"['{k}']" for k in name.removesuffix(".npy").split("/"))] = tuple(shape)
        return out
    item, in_state = _orbax_item(path, step)
    meta = ocp.PyTreeCheckpointer().metadata(item)
    tree = getattr(meta, "item_metadata", meta)
    tree = getattr(tree, "tree", tree)
    tree = tree["params"] if in_state else tree
    return {jax.tree_util.keystr(k): tuple(v.shape)
            for k, v in jax.tree_util.tree_flatten_with_path(tree, is_leaf=lambda x: hasattr(x, "shape"))[0]}


def _orbax_item(path: Path, step: int | None) -> tuple[Path, bool]:
    """(orbax item directory, whether the params sit under "params" in a whole train state)."""
    if (path / "params").is_dir():  # a `sc3 convert` output: params only
        return (path / "params").absolute(), False
    # a reader writes nothing: a manager would create a missing checkpoints/ directory
    step = ocp.CheckpointManager(path.absolute() / "checkpoints").latest_step() \
        if step is None and (path / "checkpoints").is_dir() else step
    if step is None:
        raise FileNotFoundError(f"no checkpoint under {path}/checkpoints (and no params.npz or params/)")
    return path.absolute() / "checkpoints" / str(step) / "state", True


def identity(path: str | Path, step: int | None = None) -> dict:
    """What a store records of the saved model at ``path`` that its rollouts came from: ``{"sha256": ...,
    "step": N}`` -- a content hash of the files that decide them (config.json, norm_stats.json, the params that
    :func:`load_params` reads: params.npz, params/ or the checkpoint of ``step``, default the latest; a learned
    tokenizer's files, the learned state head) and the training step of a workdir's checkpoint (None for an export,
    which records none). Cheap: one sha256 pass over a few MB to a few hundred."""
    path = Path(path)
    cfg = read_config(path)
    files = [("config.json", path / "config.json"), ("norm_stats.json", path / "norm_stats.json"),
             ("state_head.npz", path / "state_head.npz")]
    if (path / "params.npz").exists():
        files.append(("params.npz", path / "params.npz"))
    else:
        item, in_state = _orbax_item(path, step)
        step = int(item.parent.name) if in_state else None
        files += [(f"params/{f.relative_to(item)}", f) for f in sorted(item.rglob("*")) if f.is_file()]
    tok = Path(cfg.model.tokenizer_path) if cfg.model.tokenizer == "conv_ae" and cfg.model.tokenizer_path else None
    if tok is not None and tok.is_dir():  # a few MB; a pretrained video VAE (GBs) is named by its path in config.json
        files += [(f"tokenizer/{f.relative_to(tok)}", f) for f in sorted(tok.rglob("*")) if f.is_file()]
    return {"sha256": files_sha256([(n, f) for n, f in files if f.is_file()]), "step": step}


def files_sha256(files: list[tuple[str, Path]]) -> str:
    """sha256 over (name, size, bytes) of each file, in the order given: a renamed, cut or edited file changes it."""
    import hashlib

    h = hashlib.sha256()
    for name, f in files:
        h.update(f"{name}\0{f.stat().st_size}\0".encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 22), b""):
                h.update(block)
    return h.hexdigest()


def _load_npz(path: Path, target) -> dict:
    """``{"a/b/c": array}`` (written by :func:`save`) -> params placed as ``target`` says."""
    with atomic.open_npz(path, NPZ_FIX) as z:
        names = ["/".join(k.key for k in kp) for kp, _ in jax.tree_util.tree_flatten_with_path(target)[0]]
        missing = [n for n in names if n not in z.files]
        if missing:
            raise UserError(f"{path}: no array {missing[0]!r} ({len(missing)} of the config's {len(names)} params "
                            f"missing): not this config's model; {NPZ_FIX}")

        def leaf(kp, t):
            name = "/".join(k.key for k in kp)
            x = numeric(np.asarray(z[name]), f"{path}: {name}", NPZ_FIX)
            if x.shape != t.shape or not np.all(np.isfinite(x)):
                raise UserError(f"{path}: {name} is {list(x.shape)}" + ("" if x.shape != t.shape else " with NaN/inf")
                                + f", the config needs {list(t.shape)} finite; {NPZ_FIX}")
            if name + SCALE_SUFFIX in z.files:  # int8 export: dequantise
                x = x.astype(np.float32) * z[name + SCALE_SUFFIX].astype(np.float32)
            x = x.astype(t.dtype)
            return jax.make_array_from_callback(t.shape, t.sharding, lambda idx: x[idx])
        return jax.tree_util.tree_map_with_path(leaf, target)


# ================================================================================================================
# Writing
# ================================================================================================================
SCALE_SUFFIX = "@scale"  # params.npz entry holding an int8 matrix's scales
NPZ_FIX = "restore it from a copy, or export the model again (checkpoint.export)"
INT8_MIN_SIZE = 4096  # smaller arrays (norms, biases, embeddings of a few rows) stay float16: nothing to gain


def export(workdir: str | Path, out: str | Path, dtype=np.float16) -> Path:
    """Write a run's latest params (as ``dtype``), config and norm stats to ``out`` -- small enough to commit -- and
    its learned robot state (``state_head.npz``) and lineage (``lineage.json``) where it has them."""
    cfg, stats, params = load(workdir)
    try:  # a run whose config.json predates its robot facts: recorded from its store while that is here
        cfg = with_robot(cfg, _recorded_robot(Path(workdir), cfg))
    except UserError:
        pass  # not here either: exported as it is (read_robot then names the field to add)
    out = save(out, cfg, stats, params, dtype)
    for name in ("state_head.npz", "lineage.json"):  # its learned robot state; its compute since initialisation
        src = Path(workdir) / name
        if src.exists():
            with atomic.replacing(out / name) as tmp:
                shutil.copyfile(src, tmp)
    return out


def save(out: str | Path, cfg: Config, stats: NormStats, params, dtype=np.float16, extra=None) -> Path:
    """An exported world model at ``out``, written as one (``atomic.replacing_dir``): a reader, a failure or a kill
    sees the previous model or this one whole, never one's params with the other's config; files another tool put
    in ``out`` (``diagnose.json``, ``state_reader.npz``) stay. A learned tokenizer (``conv_ae``) travels with the
    model: copied to ``out/tokenizer`` (float32: a few MB) and referred to by that relative path, which
    :func:`read_config` resolves against the model directory. ``dtype="int8"`` stores every matrix as int8 with a
    float16 scale per output channel (:func:`quantize_int8`) and the rest as float16: half the bytes, for models
    that must fit a repository. ``extra(tmp)``: writes more files into the new directory before it takes ``out``'s
    place."""
    out = Path(out)
    int8 = isinstance(dtype, str) and dtype == "int8"
    arrays = {}
    for k, v in _flatten(params):
        v = np.asarray(v)
        if int8 and v.ndim >= 2 and v.size >= INT8_MIN_SIZE:
            arrays[k], arrays[k + SCALE_SUFFIX] = quantize_int8(v)
        else:
            arrays[k] = v.astype(np.float16 if int8 else dtype)
    with atomic.replacing_dir(out) as tmp:
        if cfg.model.tokenizer == "conv_ae":  # copied even from out/tokenizer itself: the new directory needs it
            shutil.copytree(Path(cfg.model.tokenizer_path), tmp / "tokenizer")
            cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, tokenizer_path="tokenizer"))
        atomic.save_npz(tmp / "params.npz", **arrays)
        atomic.write_json(tmp / "config.json", dataclasses.asdict(cfg))
        stats.save(tmp / "norm_stats.json")
        if extra is not None:  # more files of the same model (a trunk's optimizer state), in the same one step
            extra(tmp)
    return out


def quantize_int8(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric int8 with one float16 scale per output channel (the last axis; per layer for scanned [L, ...]
    stacks): ``w ~= q * scale``, error at most half a step of that channel's largest weight / 127."""
    w = np.asarray(w, np.float32)
    axes = tuple(range(w.ndim - 1)) if w.ndim == 2 else tuple(range(1, w.ndim - 1))
    scale = (np.abs(w).max(axis=axes, keepdims=True) / 127.0).astype(np.float16)
    safe = np.where(scale == 0, 1.0, scale.astype(np.float32))
    q = np.clip(np.round(w / safe), -127, 127).astype(np.int8)
    return q, scale


def save_converted(out: str | Path, cfg: Config, params) -> Path:
    """A ``sc3 convert`` output at ``out``: config.json and the params as an orbax tree (no norm stats: a converted
    model has not seen our data)."""
    out = Path(out)
    ckpt = ocp.StandardCheckpointer()
    ckpt.save((out / "params").absolute(), params)
    ckpt.wait_until_finished()
    atomic.write_json(out / "config.json", dataclasses.asdict(cfg))  # last: a directory without it is not a model
    return out


def _flatten(tree, prefix=""):
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}/")
        else:
            yield f"{prefix}{k}", v
