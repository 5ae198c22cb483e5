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

import argparse
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

from sc3_jax.data.episodes import EpisodeStore
from sc3_jax.evaluate.metrics import psnr_from_mse
from sc3_jax.model import autoencoder as ae


@dataclasses.dataclass(frozen=True)
class TokenizerTrainConfig:
    data: str = "runs/bussing/demos"
    heldout: str | None = None  # a separate episode store for the held-out evaluation (default: no evaluation)
    workdir: str = "runs/tokenizer"
    views: tuple[str, ...] = ("left", "right", "wrist")
    steps: int = 3000
    batch_size: int = 32
    lr: float = 2e-3
    warmup_steps: int = 100
    moving_weight: float = 4.0
    moving_threshold: float = 0.06  # |pixel - temporal median| in [-1, 1] units (any channel) to count as moving
    seed: int = 0
    ckpt_every: int = 250
    eval_frames: int = 256  # held-out images per view for the evaluation
    progress: bool = True


# -- data ---------------------------------------------------------------------------------------------------------
class ImageSampler:
    """Random single-view images with their moving-pixel masks; batch i is a pure function of (seed, i)."""

    def __init__(self, root: str, views: tuple[str, ...], cache: int = 512):
        self.store = EpisodeStore(root)
        self.ids = self.store.episode_ids()
        if not self.ids:
            raise ValueError(f"{root}: no episodes to train a tokenizer on")
        missing = [v for v in views if v not in self.store.views]
        if missing:
            raise ValueError(f"{root}: dataset views {self.store.views} lack {missing}")
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

    def draw(self, rng: np.random.Generator, n: int, threshold: float):
        """(images uint8 [n, H, W, 3], moving float32 [n, H, W, 1], view index int [n])."""
        eps = rng.integers(len(self.ids), size=n)
        ts = (rng.random(n) * self.lengths[eps]).astype(np.int64)
        vs = rng.integers(len(self.views), size=n)
        imgs, masks = [], []
        for e, t, v in zip(eps, ts, vs):
            ep, med = self._episode(int(e))
            img = np.asarray(ep.frames[self.views[v]][t])
            imgs.append(img)
            diff = np.abs(img.astype(np.float32) - med[self.views[v]]).max(-1, keepdims=True) / 127.5
            masks.append((diff > threshold).astype(np.float32))
        return np.stack(imgs), np.stack(masks), vs

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
    and over moving pixels."""
    sampler = ImageSampler(store_root, tuple(views))
    rt = jax.jit(lambda x: ae.decode(params, stats, ae.encode(params, stats, x)))
    out = {}
    rng = np.random.default_rng(seed)
    for vi, v in enumerate(views):
        imgs, masks = [], []
        while sum(len(i) for i in imgs) < n:
            im, mk, vs = sampler.draw(rng, 256, threshold)
            imgs.append(im[vs == vi])
            masks.append(mk[vs == vi])
        im, mk = np.concatenate(imgs)[:n], np.concatenate(masks)[:n]
        rec = np.concatenate([np.asarray(rt(im[i:i + 128])) for i in range(0, n, 128)])
        rec = np.clip(np.round((rec + 1) * 127.5), 0, 255).astype(np.uint8)
        out[v] = {"psnr": psnr(rec, im), "psnr_moving": psnr(rec, im, mk), "moving_fraction": float(mk.mean())}
    return out


def train(cfg: TokenizerTrainConfig, ae_cfg: ae.AEConfig, stop_at: int | None = None) -> dict:
    """Train (or resume) to ``cfg.steps`` (or stop after ``stop_at``), then export. Returns the export's summary."""
    workdir = Path(cfg.workdir).absolute()
    workdir.mkdir(parents=True, exist_ok=True)
    meta = {"train": dataclasses.asdict(cfg), "ae": dataclasses.asdict(ae_cfg)}
    cfg_path = workdir / "tokenizer_config.json"
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        if old["ae"] != meta["ae"]:
            raise ValueError(f"{workdir} holds a tokenizer with architecture {old['ae']}; this run asks for "
                             f"{meta['ae']}: use another --workdir")
    cfg_path.write_text(json.dumps(meta, indent=1))
    sampler = ImageSampler(cfg.data, cfg.views)
    h, w = sampler.image_size
    if h % ae_cfg.downsample or w % ae_cfg.downsample:
        raise ValueError(f"image size {(h, w)} is not a multiple of the downsampling {ae_cfg.downsample}")
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
        result["heldout"] = evaluate(params, stats, cfg.heldout, cfg.views, cfg.eval_frames, cfg.moving_threshold)
    (out / "eval.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="sc3 train-tokenizer", description=__doc__.split("\n\n")[0])
    for f in dataclasses.fields(TokenizerTrainConfig):
        _add(p, f, TokenizerTrainConfig)
    for f in dataclasses.fields(ae.AEConfig):
        _add(p, f, ae.AEConfig, prefix="ae.")
    p.add_argument("--export-only", action="store_true", help="write workdir/tokenizer from the latest checkpoint")
    a = vars(p.parse_args(argv))
    cfg = TokenizerTrainConfig(**{f.name: a[f.name] for f in dataclasses.fields(TokenizerTrainConfig)})
    ae_cfg = ae.AEConfig(**{f.name: a["ae." + f.name] for f in dataclasses.fields(ae.AEConfig)})
    if a["export_only"]:
        cfg = dataclasses.replace(cfg, steps=0)
        mngr = ocp.CheckpointManager(Path(cfg.workdir).absolute() / "checkpoints")
        if mngr.latest_step() is None:
            raise SystemExit(f"{cfg.workdir}: no checkpoint to export")
        opt = make_optimizer(cfg)
        params = ae.init(ae_cfg, jax.random.key(cfg.seed))
        state = mngr.restore(mngr.latest_step(), args=ocp.args.StandardRestore(
            {"params": params, "opt_state": opt.init(params), "step": jnp.zeros((), jnp.int32)}))
        result = export(cfg, ae_cfg, state["params"], ImageSampler(cfg.data, cfg.views))
    else:
        result = train(cfg, ae_cfg)
    print(json.dumps(result, indent=1))
    return 0


def _add(p, f, cls, prefix=""):
    default = getattr(cls(), f.name)
    name = "--" + (prefix + f.name).replace("_", "-")
    dest = prefix + f.name
    if isinstance(default, bool):
        p.add_argument(name, dest=dest, action=argparse.BooleanOptionalAction, default=default)
    elif isinstance(default, tuple):
        p.add_argument(name, dest=dest, nargs="+", default=default, type=type(default[0]) if default else str)
    else:
        typ = type(default) if default is not None else str
        p.add_argument(name, dest=dest, type=typ, default=default)


if __name__ == "__main__":
    raise SystemExit(main())
