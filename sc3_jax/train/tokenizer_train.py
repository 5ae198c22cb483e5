"""`sc3 train-tokenizer`: train the convolutional autoencoder (``model/autoencoder.py``) on an episode store.

Samples are single (episode, frame, view) images drawn uniformly from the store (views share one autoencoder).
The loss is L1 + L2 on [-1, 1] pixels, with pixels that differ from the episode's temporal median of that view (the
arm and the objects that move: what the world model exists to render) weighted ``moving_weight`` times more:
they are a few percent of the frame and would otherwise barely register in a mean.

Resumable: orbax checkpoints of (params, optimizer state, step) in ``workdir/checkpoints``; the batch of step i is a
pure function of (seed, i), so a resumed run sees exactly the batches an uninterrupted one would. At the end (and
with ``--export-only``) the autoencoder with its latent statistics is written to ``workdir/tokenizer`` (the directory
``model.tokenizer_path`` points at), and a held-out evaluation to ``workdir/tokenizer/eval.json``.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp

from sc3_jax.core import atomic
from sc3_jax.data.episodes import EpisodeStore
from sc3_jax.core.errors import UserError
from sc3_jax.measures.metrics import psnr_from_mse
from sc3_jax.model import autoencoder as ae
from sc3_jax.core.tokenizer_config import TokenizerTrainConfig


# -- data ---------------------------------------------------------------------------------------------------------
class ImageSampler:
    """Random single-view images with their moving-pixel masks; batch i is a pure function of (seed, i)."""

    def __init__(self, root: str, views: tuple[str, ...] | None, cache: int = 512):
        self.store = EpisodeStore(root)
        self.ids = self.store.episode_ids()
        if not self.ids:
            raise UserError(f"{root}: no episodes to train a tokenizer on (--data / --heldout: an episode store)")
        views = tuple(self.store.views) if views is None else views
        missing = [v for v in views if v not in self.store.views]
        if missing:
            raise UserError(f"{root}: dataset views {self.store.views} lack {missing} (--views)")
        self.views = tuple(views)
        self.lengths = np.array([self.store.load(e, mmap=True, validate=False).length for e in self.ids])
        self._cache: collections.OrderedDict = collections.OrderedDict()
        self._max = cache

    @property
    def image_size(self) -> tuple[int, int]:
        return tuple(self.store.image_size)

    def _episode(self, n: int):
        if n in self._cache:
            self._cache.move_to_end(n)
            return self._cache[n]
        ep = self.store.load(self.ids[n], mmap=True, validate=False)
        med = {v: np.median(np.asarray(ep.frames[v]), axis=0).astype(np.float32) for v in self.views}
        self._cache[n] = (ep, med)
        while len(self._cache) > self._max:
            self._cache.popitem(last=False)
        return ep, med

    def draw(self, rng: np.random.Generator, n: int, threshold: float, medians: bool = False):
        """(images uint8 [n, H, W, 3], moving float32 [n, H, W, 1], view index int [n]) and, with ``medians``, each
        image's episode temporal median of its view (uint8 [n, H, W, 3]: the scene with nothing moving)."""
        eps = rng.integers(len(self.ids), size=n)
        ts = (rng.random(n) * self.lengths[eps]).astype(np.int64)
        vs = rng.integers(len(self.views), size=n)
        imgs, masks, meds = [], [], []
        for e, t, v in zip(eps, ts, vs):
            ep, med = self._episode(int(e))
            img = np.asarray(ep.frames[self.views[v]][t])
            imgs.append(img)
            diff = np.abs(img.astype(np.float32) - med[self.views[v]]).max(-1, keepdims=True) / 127.5
            masks.append((diff > threshold).astype(np.float32))
            meds.append(med[self.views[v]])
        out = np.stack(imgs), np.stack(masks), vs
        return out + (np.clip(np.round(np.stack(meds)), 0, 255).astype(np.uint8),) if medians else out

    def batch(self, seed: int, i: int, n: int, threshold: float):
        return self.draw(np.random.default_rng([seed, i]), n, threshold)


# -- training -----------------------------------------------------------------------------------------------------
def make_optimizer(cfg: TokenizerTrainConfig):
    sched = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, cfg.warmup_steps, max(cfg.steps, cfg.warmup_steps + 1),
                                               cfg.lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(sched, b2=0.99))


def loss_fn(params, images_u8, moving, moving_weight: float):
    x = images_u8.astype(jnp.float32) / 127.5 - 1.0
    y = ae.decode_raw(params, ae.encode_raw(params, x))
    w = 1.0 + moving_weight * moving
    err = y - x
    loss = jnp.mean(w * (jnp.abs(err) + err * err)) / jnp.mean(w)
    return loss, {"loss": loss, "mse": jnp.mean(err * err)}


def make_step(cfg: TokenizerTrainConfig):
    opt = make_optimizer(cfg)

    @jax.jit
    def step(state, images, moving):
        (_, metrics), g = jax.value_and_grad(loss_fn, has_aux=True)(state["params"], images, moving,
                                                                    cfg.moving_weight)
        updates, opt_state = opt.update(g, state["opt_state"], state["params"])
        return {"params": optax.apply_updates(state["params"], updates), "opt_state": opt_state,
                "step": state["step"] + 1}, metrics

    return opt, step


def latent_stats(params, sampler: ImageSampler, seed: int, n: int = 1024) -> dict:
    """Per-channel mean and std of the raw latents over n random training images."""
    imgs, _, _ = sampler.draw(np.random.default_rng([seed, 10 ** 9]), n, 1.0)
    enc = jax.jit(lambda p, x: ae.encode_raw(p, x.astype(jnp.float32) / 127.5 - 1.0))
    z = np.concatenate([np.asarray(enc(params, imgs[i:i + 128])) for i in range(0, n, 128)])
    z = z.reshape(-1, z.shape[-1])
    return {"mean": jnp.asarray(z.mean(0)), "std": jnp.asarray(np.maximum(z.std(0), 1e-3))}


def psnr(pred_u8: np.ndarray, true_u8: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB over all pixels, or over the pixels where ``mask`` [..., H, W, 1] is set."""
    err = (pred_u8.astype(np.float64) - true_u8.astype(np.float64)) ** 2
    if mask is not None:
        m = np.broadcast_to(mask > 0, err.shape)
        if not m.any():
            return float("nan")
        mse = err[m].mean()
    else:
        mse = err.mean()
    return float(psnr_from_mse(max(mse, 1e-10)))  # floored: identical frames read ~148 dB, not inf


def evaluate(params, stats, store_root: str, views, n: int, threshold: float, seed: int = 1) -> dict:
    """Reconstruction PSNR per view on ``n`` random images of each view of a held-out store: over the whole frame
    and over moving pixels; beside each, the same PSNR of a static baseline, the episode's temporal median of that
    view (what a tokenizer that drops everything that moves would score: on moving pixels the tokenizer must beat
    it by far)."""
    sampler = ImageSampler(store_root, tuple(views))
    rt = jax.jit(lambda x: ae.decode(params, stats, ae.encode(params, stats, x)))
    out = {}
    rng = np.random.default_rng(seed)
    for vi, v in enumerate(views):
        imgs, masks, meds = [], [], []
        while sum(len(i) for i in imgs) < n:
            im, mk, vs, md = sampler.draw(rng, 256, threshold, medians=True)
            imgs.append(im[vs == vi])
            masks.append(mk[vs == vi])
            meds.append(md[vs == vi])
        im, mk, md = np.concatenate(imgs)[:n], np.concatenate(masks)[:n], np.concatenate(meds)[:n]
        rec = np.concatenate([np.asarray(rt(im[i:i + 128])) for i in range(0, n, 128)])
        rec = np.clip(np.round((rec + 1) * 127.5), 0, 255).astype(np.uint8)
        out[v] = {"psnr": psnr(rec, im), "psnr_moving": psnr(rec, im, mk), "moving_fraction": float(mk.mean()),
                  "static_psnr": psnr(md, im), "static_psnr_moving": psnr(md, im, mk)}
    return out


def _data(cfg: TokenizerTrainConfig) -> str:
    """``cfg.data``, or one line saying it is needed (no store is a default: none is every robot's)."""
    if not cfg.data:
        raise UserError("--data: give the episode store to train the tokenizer on (sc3 train-tokenizer --data STORE)")
    return cfg.data


def train(cfg: TokenizerTrainConfig, ae_cfg: ae.AEConfig, stop_at: int | None = None) -> dict:
    """Train (or resume) to ``cfg.steps`` (or stop after ``stop_at``), then export. Returns the export's summary."""
    _data(cfg)  # before the workdir is made
    workdir = Path(cfg.workdir).absolute()
    workdir.mkdir(parents=True, exist_ok=True)
    meta = {"train": dataclasses.asdict(cfg), "ae": dataclasses.asdict(ae_cfg)}
    cfg_path = workdir / "tokenizer_config.json"
    if cfg_path.exists():
        old = atomic.read_json(cfg_path, "restore it, or use another --workdir")
        if old["ae"] != meta["ae"]:
            raise UserError(f"{workdir} holds a tokenizer with architecture {old['ae']}; this run asks for "
                            f"{meta['ae']}: use another --workdir")
    atomic.write_json(cfg_path, meta)
    sampler = ImageSampler(cfg.data, cfg.views)
    h, w = sampler.image_size
    if h % ae_cfg.downsample or w % ae_cfg.downsample:
        raise UserError(f"{cfg.data}: image size {(h, w)} is not a multiple of --ae.downsample {ae_cfg.downsample}")
    opt, step_fn = make_step(cfg)
    mngr = ocp.CheckpointManager(workdir / "checkpoints",
                                 options=ocp.CheckpointManagerOptions(max_to_keep=2, save_interval_steps=cfg.ckpt_every))
    params = ae.init(ae_cfg, jax.random.key(cfg.seed))
    state = {"params": params, "opt_state": opt.init(params), "step": jnp.zeros((), jnp.int32)}
    if mngr.latest_step() is not None:
        state = mngr.restore(mngr.latest_step(), args=ocp.args.StandardRestore(state))
    start = int(state["step"])
    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=cfg.steps, initial=start, desc="train-tokenizer", dynamic_ncols=True)
    atomic.drop_cut_line(workdir / "metrics.jsonl")  # a line cut by a kill would glue to the next one
    atomic.drop_rows_after(workdir / "metrics.jsonl", start)  # steps past the checkpoint are trained again
    log = (workdir / "metrics.jsonl").open("a")
    t0 = time.perf_counter()
    end = cfg.steps if stop_at is None else min(stop_at, cfg.steps)
    for i in range(start, end):
        imgs, moving, _ = sampler.batch(cfg.seed, i, cfg.batch_size, cfg.moving_threshold)
        state, m = step_fn(state, imgs, moving)
        if (i + 1) % 25 == 0 or i + 1 == cfg.steps:
            row = {"step": i + 1, **{k: float(v) for k, v in m.items()},
                   "psnr_train": float(psnr_from_mse(max(float(m["mse"]), 1e-10), 2.0)),
                   "elapsed_s": time.perf_counter() - t0}
            log.write(json.dumps(row) + "\n")
            log.flush()
            if bar is not None:
                bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['psnr_train']:.1f}")
        if bar is not None:
            bar.update(1)
        mngr.save(i + 1, args=ocp.args.StandardSave(state), force=i + 1 == end)
    mngr.wait_until_finished()
    mngr.close()
    log.close()
    if bar is not None:
        bar.close()
    return export(cfg, ae_cfg, state["params"], sampler)


def export(cfg: TokenizerTrainConfig, ae_cfg: ae.AEConfig, params, sampler: ImageSampler) -> dict:
    out = Path(cfg.workdir).absolute() / "tokenizer"
    stats = latent_stats(params, sampler, cfg.seed)
    ae.save(out, ae_cfg, sampler.image_size, params, stats)
    result = {"params": ae.count(params), "latent": [sampler.image_size[0] // ae_cfg.downsample,
                                                     sampler.image_size[1] // ae_cfg.downsample,
                                                     ae_cfg.latent_channels]}
    if cfg.heldout:
        result["heldout"] = evaluate(params, stats, cfg.heldout, sampler.views, cfg.eval_frames,
                                     cfg.moving_threshold)
    atomic.write_json(out / "eval.json", result)
    return result


def export_latest(cfg: TokenizerTrainConfig, ae_cfg: ae.AEConfig) -> dict:
    """``export`` of the latest checkpoint in ``cfg.workdir`` (no training step): ``sc3 train-tokenizer
    --export-only``."""
    root = Path(cfg.workdir).absolute() / "checkpoints"
    mngr = ocp.CheckpointManager(root) if root.is_dir() else None  # (a manager would create the directory)
    if mngr is None or mngr.latest_step() is None:
        raise UserError(f"{cfg.workdir}: no checkpoint to export (train first: the same command without "
                        f"--export-only)")
    cfg = dataclasses.replace(cfg, steps=0)
    opt = make_optimizer(cfg)
    params = ae.init(ae_cfg, jax.random.key(cfg.seed))
    state = mngr.restore(mngr.latest_step(), args=ocp.args.StandardRestore(
        {"params": params, "opt_state": opt.init(params), "step": jnp.zeros((), jnp.int32)}))
    mngr.close()
    return export(cfg, ae_cfg, state["params"], ImageSampler(_data(cfg), cfg.views))
