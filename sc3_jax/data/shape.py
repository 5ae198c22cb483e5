"""A world model's shape from its data: views, view count, image size and action dimension come from the episode
store's ``dataset.json`` unless the user set them, and a user-set (or trained) shape that the data contradicts is a
one-line ``UserError`` naming both sides, before anything compiles.

- :func:`shape_from_dataset` (``sc3 train``): fills ``data.views``, ``model.num_views``, ``data.image_size``,
  ``model.action_dim``, ``data.fps`` and ``data.state_dim`` from the store (so a saved model's config.json records
  its robot's facts: ``checkpoint.read_robot``), and turns pseudo-actions off (``data.pseudo_action_prob`` 0) where
  the data cannot give them (no measured end-effector pose, or actions that are not delta_ee), and cross-view
  inpainting off (``modes.probs``' second share to the other two, in proportion) where the model sees one view; the
  fields named in ``explicit`` are checked instead of filled. The entries ``data.window_weights`` names must be the
  store's (checked, not filled).
- :func:`check_shape` (a trained model against a store of initial conditions, ``sc3 rollout``): checks only.
- :func:`explicit_fields`: which of those fields a command line set (``--SECTION.FIELD``).

The imagined robot state the model is conditioned on lives in the action's space (``data/action_space.py``), so
its size is ``model.action_dim``; a dataset whose actions need a recorded state of another size (velocities) is
refused when the store is created.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Collection, Iterable

from sc3_jax.data import window_weights
from sc3_jax.data.episodes import EpisodeStore
from sc3_jax.core.errors import UserError

# the fields this module fills (``section.field``), in the order they are decided
SHAPE_FIELDS = ("data.views", "model.num_views", "data.image_size", "model.action_dim", "data.pseudo_action_prob",
                "modes.probs", "data.fps", "data.state_dim")


def shape_from_dataset(cfg, store, explicit: Collection[str] = ()):
    """``cfg`` with its shape fields taken from ``store`` (an ``EpisodeStore`` or its path) unless named in
    ``explicit`` (dotted ``section.field`` names, e.g. from :func:`explicit_fields`); an explicit value the data
    contradicts raises a one-line UserError naming both. Views: every view of the dataset, in its order (an explicit
    subset of them is fine). Returns a new Config; ``cfg`` is not modified."""
    store = _open(store)
    explicit = frozenset(explicit)  # other fields may be named too: they are not this module's
    where = f"{store.root}/dataset.json"
    data, model = cfg.data, cfg.model
    views = tuple(data.views) if "data.views" in explicit else tuple(store.views)
    _check_views(views, store, where)
    if "model.num_views" in explicit:
        _check_num_views(model.num_views, views, where)
    num_views = model.num_views if "model.num_views" in explicit else len(views)
    image_size = tuple(data.image_size) if "data.image_size" in explicit else tuple(store.image_size)
    _check_image_size(image_size, store, where)
    action_dim = model.action_dim if "model.action_dim" in explicit else store.action_space.dim
    _check_action_dim(action_dim, store, where)
    fps = data.fps if "data.fps" in explicit else float(store.fps)
    if fps is None or abs(float(fps) - float(store.fps)) > 1e-9:
        raise UserError(f"data.fps={fps}, but {where} has fps {store.fps}")
    recorded = int(store.state_dim or 0)  # 0: the store records no state
    state_dim = data.state_dim if "data.state_dim" in explicit else recorded
    if state_dim != recorded:
        raise UserError(f"data.state_dim={state_dim}, but {where} records "
                        f"{f'a {recorded}-D state' if recorded else 'no state'}")
    window_weights.check(data, store)  # entries the store lacks: one line now, not after the latents are cached
    refusal = store.action_space.pseudo_refusal(store.has_pose)
    pseudo = data.pseudo_action_prob
    if refusal and pseudo > 0:
        if "data.pseudo_action_prob" in explicit:
            raise UserError(f"data.pseudo_action_prob={pseudo}, but {where}: {refusal}")
        pseudo = 0.0
    return dataclasses.replace(
        cfg, data=dataclasses.replace(data, views=views, image_size=image_size, pseudo_action_prob=pseudo,
                                      fps=float(fps), state_dim=int(state_dim)),
        model=dataclasses.replace(model, num_views=num_views, action_dim=action_dim),
        modes=dataclasses.replace(cfg.modes, probs=_mode_probs(cfg.modes.probs, views, "modes.probs" in explicit,
                                                                where)))


def _mode_probs(probs, views: tuple[str, ...], explicit: bool, where: str) -> tuple[float, float, float]:
    """Cross-view inpainting needs a second view to inpaint from: with one view its share goes to forward and inverse
    dynamics in proportion (an explicit share is refused instead)."""
    fd, cvi, inv = (float(p) for p in probs)
    if len(views) > 1 or cvi <= 0:
        return (fd, cvi, inv)
    if explicit:
        raise UserError(f"modes.probs={list(probs)}: cross-view inpainting (the second share) needs two views or "
                        f"more; the model sees one ({views[0]!r} of {where}): set it to 0")
    if fd + inv <= 0:
        raise UserError(f"modes.probs={list(probs)}: with one view ({where}) only forward and inverse dynamics can "
                        "train: give them a share")
    return (fd / (fd + inv), 0.0, inv / (fd + inv))


def check_shape(cfg, store) -> None:
    """A trained model's shape (``cfg``) against a store it will read (e.g. initial conditions): views, view count,
    image size and action dimension; one-line UserError naming both sides on any mismatch."""
    store = _open(store)
    where = f"{store.root}/dataset.json"
    _check_views(tuple(cfg.data.views), store, where)
    _check_num_views(cfg.model.num_views, tuple(cfg.data.views), where)
    _check_image_size(tuple(cfg.data.image_size), store, where)
    _check_action_dim(cfg.model.action_dim, store, where)


def explicit_fields(argv: Iterable[str]) -> frozenset[str]:
    """The ``section.field`` names a command line sets (``--data.image-size 24 32``, ``--model.action_dim=14``),
    dashes read as underscores: what :func:`shape_from_dataset` must check rather than fill."""
    out = set()
    for tok in argv:
        if tok.startswith("--") and "." in tok:
            out.add(tok[2:].split("=", 1)[0].replace("-", "_"))
    return frozenset(out)


def _open(store):
    return EpisodeStore(store) if isinstance(store, (str, os.PathLike)) else store


def _check_views(views: tuple[str, ...], store, where: str) -> None:
    missing = [v for v in views if v not in store.views]
    if missing:
        raise UserError(f"data.views={list(views)}, but {where} has views {list(store.views)} (no {missing})")
    if not views:
        raise UserError(f"data.views is empty; {where} has views {list(store.views)}")


def _check_num_views(num_views: int, views: tuple[str, ...], where: str) -> None:
    if num_views != len(views):
        raise UserError(f"model.num_views={num_views}, but data.views has {len(views)} ({list(views)}; "
                        f"{where})")


def _check_image_size(image_size: tuple[int, int], store, where: str) -> None:
    if tuple(image_size) != tuple(store.image_size):
        raise UserError(f"data.image_size={list(image_size)}, but {where} has image_size {list(store.image_size)}")


def _check_action_dim(action_dim: int, store, where: str) -> None:
    space = store.action_space
    if action_dim != space.dim:
        raise UserError(f"model.action_dim={action_dim}, but {where} declares {space.dim}-D {space.kind} actions")
