"""The small pixel network shared by the policy zoo and the perception scorer: a conv trunk over each 64x64 view
(with coordinate channels) ending in spatial-softmax keypoints + pooled keypoint logits, then an MLP head.
Keypoints are image-plane coordinates, which is what both users need (where is the object / the container)."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from sc3_jax.policies.convnet import conv, conv_init

NET_SIZE = 64


def init_trunk(ks, n_kp: int, widths: tuple[int, int, int] = (16, 32, 32)) -> dict:
    """``ks``: 4 keys (one per conv layer); ``widths``: output channels of the first three conv layers (the
    forward pass reads every width from the weights' shapes, so any widths load and run)."""
    w1, w2, w3 = widths
    return {"c1": conv_init(ks[0], 3, 5, w1), "c2": conv_init(ks[1], 3, w1, w2),
            "c3": conv_init(ks[2], 3, w2, w3), "c4": conv_init(ks[3], 3, w3, n_kp)}


def trunk_features(net: dict, images: jax.Array) -> jax.Array:
    """images uint8 [B, V, H, W, 3] (resized to 64x64 if needed) -> [B, V * 3 * n_kp]: per view, the keypoints'
    expected (x, y) under a spatial softmax and their tanh-squashed max logits (n_kp read from ``net["c4"]``)."""
    b, v, h, w, _ = images.shape
    x = images.reshape(b * v, h, w, 3).astype(jnp.float32) / 255.0
    if (h, w) != (NET_SIZE, NET_SIZE):
        x = jax.image.resize(x, (b * v, NET_SIZE, NET_SIZE, 3), "linear")
    ys, xs = jnp.meshgrid(jnp.linspace(-1, 1, NET_SIZE), jnp.linspace(-1, 1, NET_SIZE), indexing="ij")
    coords = jnp.broadcast_to(jnp.stack([xs, ys], -1), (b * v, NET_SIZE, NET_SIZE, 2))
    x = jnp.concatenate([x - 0.5, coords], -1)
    x = jax.nn.relu(conv(x, net["c1"], 2))
    x = jax.nn.relu(conv(x, net["c2"], 2))
    x = jax.nn.relu(conv(x, net["c3"], 1))
    x = conv(x, net["c4"], 1)  # [BV, 16, 16, K]
    hh, ww = x.shape[1:3]
    n_kp = net["c4"]["w"].shape[-1]
    logits = x.reshape(b * v, hh * ww, n_kp)
    att = jax.nn.softmax(logits, axis=1)
    gy, gx = jnp.meshgrid(jnp.linspace(-1, 1, hh), jnp.linspace(-1, 1, ww), indexing="ij")
    grid = jnp.stack([gx.reshape(-1), gy.reshape(-1)], -1)  # [HW, 2]
    kp = jnp.einsum("nsk,sc->nkc", att, grid).reshape(b, v * n_kp * 2)
    pooled = jnp.max(logits, axis=1).reshape(b, v * n_kp)
    return jnp.concatenate([kp, jnp.tanh(pooled * 0.1)], -1)


