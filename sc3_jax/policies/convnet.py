"""Layers of the small pixel networks the benchmarks' policies and scorers are made of (pure JAX, params as dicts):
a convolution, a dense layer and an MLP head, with their initialisations, and their float16 files."""
from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic


def conv_init(key, k, cin, cout):
    return {"w": jax.random.normal(key, (k, k, cin, cout)) * np.sqrt(2.0 / (k * k * cin)), "b": jnp.zeros(cout)}


def dense_init(key, din, dout, scale=1.0):
    return {"w": jax.random.normal(key, (din, dout)) * np.sqrt(1.0 / din) * scale, "b": jnp.zeros(dout)}


def conv(x, p, stride):
    y = jax.lax.conv_general_dilated(x, p["w"], (stride, stride), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + p["b"]


def mlp(net: dict, f: jax.Array, layers=("d1", "d2")) -> jax.Array:
    for name in layers:
        f = jax.nn.relu(f @ net[name]["w"] + net[name]["b"])
    return f @ net["out"]["w"] + net["out"]["b"]


def save_params(path: str | Path, net: dict) -> None:
    """A net {layer: {name: array}} as float16 (a zoo policy's weights ship so: ~0.1-0.3 MB); ``load_params`` casts
    them back to float32."""
    atomic.save_npz(path, **{f"{k}/{kk}": np.asarray(v, np.float16) for k, d in net.items() for kk, v in d.items()})


def load_params(path: str | Path, fix: str) -> dict:
    """The net ``save_params`` wrote; ``fix``: what to do when the file is unreadable (one line)."""
    with atomic.open_npz(path, fix) as z:
        net: dict = {}
        for key in z.files:
            a, b = key.split("/")
            net.setdefault(a, {})[b] = jnp.asarray(z[key], jnp.float32)
    return net
