"""Tokenizer latents of an episode store, encoded once and read by the training pipeline instead of frames.

Why: the learned autoencoder's encoder costs more per window than the small world model itself on a CPU; its output
for a frame never changes, so training reads cached latents and only patchifies them (``ConvAETokenizer.from_latents``).

Layout: ``root/manifest.json`` ({"tokenizer_digest", "store", "views", "latent_shape"}) and one
``root/<episode_id>.npy`` float16 [V, T, h, w, C] per episode, written atomically; ``build`` skips episodes already
there, so an interrupted build resumes. A cache made with other tokenizer weights or views is refused.
"""
from __future__ import annotations

import collections
import hashlib
import threading
from pathlib import Path

import jax
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.data.episodes import EpisodeStore
from sc3_jax.core.errors import UserError


def tokenizer_digest(path: str | Path) -> str:
    """Hash of the tokenizer's arrays (not the file's bytes: a re-export of the same weights keeps its cache)."""
    h = hashlib.sha1()
    with atomic.open_npz(Path(path) / "ae_params.npz", "restore the tokenizer's weights") as z:
        for k in sorted(z.files):
            h.update(k.encode())
            h.update(np.ascontiguousarray(z[k]).tobytes())
    return h.hexdigest()[:16]


def build(store: EpisodeStore, tok, views: tuple[str, ...], root: str | Path, batch: int = 256,
          progress: bool = True) -> Path:
    """Encode every episode of ``store`` with ``tok`` (a ``ConvAETokenizer``) into ``root``."""
    root = Path(root)
    manifest = {"tokenizer_digest": tokenizer_digest(tok.path), "store": str(Path(store.root).absolute()),
                "views": list(views)}
    mpath = root / "manifest.json"
    if mpath.exists():
        old = atomic.read_json(mpath, f"delete {root} (the cache is rebuilt)")
        if {k: old.get(k) for k in manifest} != manifest:
            raise UserError(f"{root} holds latents of another tokenizer, store or views ({old}); remove it or "
                            f"point the cache elsewhere")
    atomic.write_json(mpath, manifest)
    enc = jax.jit(tok.encode_latents)
    ids = store.episode_ids()
    todo = [e for e in ids if not (root / f"{e}.npy").exists()]
    it = todo
    if progress and todo:
        from tqdm.auto import tqdm
        it = tqdm(todo, desc="encode latents", unit="episode", dynamic_ncols=True)
    for eid in it:
        ep = store.load(eid, mmap=True, validate=False)
        frames = np.stack([np.asarray(ep.frames[v]) for v in views])  # [V, T, H, W, 3]
        flat = frames.reshape((-1,) + frames.shape[2:])
        pad = (-len(flat)) % batch  # one compiled shape for every episode
        flat = np.concatenate([flat, np.zeros((pad,) + flat.shape[1:], flat.dtype)]) if pad else flat
        z = np.concatenate([np.asarray(enc(flat[i:i + batch])) for i in range(0, len(flat), batch)])
        z = z[:len(flat) - pad].reshape(frames.shape[:2] + z.shape[1:]).astype(np.float16)
        atomic.save_npy(root / f"{eid}.npy", z)
    return root


class LatentReader:
    """Picklable, thread-safe LRU of memory-mapped per-episode latents (episode numbers as in the window index)."""

    def __init__(self, root: str | Path, episode_ids: list[str], max_open: int = 256):
        self.root, self.episode_ids, self.max_open = str(root), list(episode_ids), max_open
        missing = [e for e in self.episode_ids if not (Path(self.root) / f"{e}.npy").exists()]
        if missing:
            raise FileNotFoundError(f"{root}: no cached latents for {len(missing)} episodes (e.g. {missing[0]}); "
                                    "run latent_cache.build")
        self._init()

    def _init(self):
        self._cache: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def __getstate__(self):
        return {k: getattr(self, k) for k in ("root", "episode_ids", "max_open")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._init()

    def window(self, ep_num: int, frame_indices) -> np.ndarray:
        """float16 [V, len(frame_indices), h, w, C]."""
        with self._lock:
            z = self._cache.get(ep_num)
            if z is None:
                z = np.load(Path(self.root) / f"{self.episode_ids[ep_num]}.npy", mmap_mode="r")
                self._cache[ep_num] = z
                while len(self._cache) > self.max_open:
                    self._cache.popitem(last=False)
            else:
                self._cache.move_to_end(ep_num)
        return np.asarray(z[:, np.asarray(frame_indices)])
