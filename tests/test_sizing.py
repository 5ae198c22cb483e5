"""Configs sized from the data (sc3_jax/train/sizing.py): a named config's token budget per frame picks the patch on any
image size and camera count, its batch keeps the step near the cost it has on the shape it was written for, and
`sc3 train` says the cost before anything compiles."""
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.train import flops, sizing
from sc3_jax.cli import main
from sc3_jax.core.config import load_config
from sc3_jax.data import synthetic

# (image size, cameras): our benchmark's, a lab's SO-101, small and large frames, one to four cameras
SHAPES = [((16, 16), 3), ((96, 128), 2), ((64, 64), 1), ((64, 64), 4), ((240, 320), 1), ((240, 320), 2)]


def _on(cfg, size, views):
    names = tuple(f"cam{i}" for i in range(views))
    fd, cvi, inv = cfg.modes.probs
    probs = (fd, cvi, inv) if views > 1 else (fd / (fd + inv), 0.0, inv / (fd + inv))  # one view: no inpainting
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, image_size=size, views=names),
                               model=dataclasses.replace(cfg.model, num_views=views),
                               modes=dataclasses.replace(cfg.modes, probs=probs))


@given(h=st.integers(1, 40), w=st.integers(1, 40), m=st.sampled_from([2, 4, 8, 16]), views=st.integers(1, 4),
       budget=st.integers(1, 400))
@settings(max_examples=60, deadline=None)
def test_the_patch_tiles_the_frame_and_no_other_side_is_nearer_the_budget(h, w, m, views, budget):
    size = (h * m, w * m)
    p = sizing.fit_patch(size, views, budget)
    assert size[0] % p == 0 and size[1] % p == 0
    tokens = views * (size[0] // p) * (size[1] // p)
    for q in range(1, min(size) + 1):
        if size[0] % q == 0 and size[1] % q == 0:
            other = views * (size[0] // q) * (size[1] // q)
            assert abs(np.log(tokens / budget)) <= abs(np.log(other / budget)) + 1e-12


def test_a_learned_tokenizer_s_patch_is_counted_in_latent_cells():
    # 80x80 frames, 4x latents (20x20), two views, 48 tokens wanted: 4-cell patches, 25 tokens a view
    assert sizing.fit_patch((80, 80), 2, 48, downsample=4) == 4


@pytest.mark.parametrize("size,views", SHAPES)
def test_tiny_costs_about_the_same_on_any_shape(size, views):
    """Tokens a frame within 2.5x of the budget and the step's FLOPs within sizing.MAX_COST of tiny's own (and not
    a starved fraction of it) on every shape: the same order of cost for the same name."""
    declared = load_config("tiny")
    cfg, _ = sizing.size_from_data(_on(declared, size, views), declared)
    p = cfg.model.patch_size
    tokens = views * (size[0] // p) * (size[1] // p)
    assert declared.model.frame_tokens / 2.5 <= tokens <= declared.model.frame_tokens * 2.5
    ratio = flops.train_step_flops(cfg) / flops.train_step_flops(declared)
    assert 1 / 6 < ratio <= sizing.MAX_COST * 1.01, (size, views, p, cfg.data.batch_size, ratio)


def test_before_sizing_two_96x128_cameras_cost_many_times_tiny_s_step():
    """What the sizing rule fixes (the first-run issue): 8-pixel patches on a lab's cameras."""
    declared = load_config("tiny")
    unsized = _on(declared, (96, 128), 2)
    assert flops.train_step_flops(unsized) > 20 * flops.train_step_flops(declared)


def test_what_the_user_names_is_kept():
    declared = load_config("tiny")
    cfg, note = sizing.size_from_data(_on(declared, (96, 128), 2), declared,
                                      explicit={"model.patch_size", "data.batch_size"})
    assert cfg.model.patch_size == 8 and cfg.data.batch_size == declared.data.batch_size and note is None


def test_a_config_without_a_budget_is_left_alone():
    declared = load_config("cpu_medium")
    assert declared.model.frame_tokens is None
    shaped = _on(declared, (96, 128), 2)
    assert sizing.size_from_data(shaped, declared) == (shaped, None)


def test_train_prints_its_cost_before_it_compiles(tmp_path, capsys, monkeypatch):
    """The cost line (tokens a frame and a sample, GFLOP, seconds and GB) comes before the compiled step runs: the
    trainer is stopped at its first call, after the line was printed."""
    from sc3_jax.train import train

    store = tmp_path / "s"
    synthetic.generate(store, 2, length=12, progress=False)

    def refuse(cfg, *a, **k):
        raise SystemExit("stopped before compiling")
    monkeypatch.setattr(train, "train", refuse)
    with pytest.raises(SystemExit, match="before compiling"):
        main(["train", "--data", str(store), "--train.workdir", str(tmp_path / "w")])
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("cost:"))
    assert "12 tokens a frame over 3 view(s) (patch 8)" in line and "GFLOP" in line and "GB" in line
    assert "--model.frame-tokens" in out


def test_a_latent_config_without_its_tokenizer_names_the_command_that_makes_it(tmp_path, capsys):
    store = tmp_path / "s"
    synthetic.generate(store, 1, length=12, progress=False)
    rc = main(["train", "--config", "so101_latent", "--data", str(store), "--model.tokenizer-path",
               str(tmp_path / "none"), "--train.workdir", str(tmp_path / "w")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "sc3 train-tokenizer --data" in err
    assert not (tmp_path / "w").exists()


def test_a_resumed_run_keeps_the_size_it_started_with(tmp_path):
    """A workdir trained before sizing existed (8-px patches, batch 32, no frame_tokens in its config.json) resumes
    with that size, not the one the sizing rule would pick today; a fresh workdir is sized."""
    import json

    from sc3_jax.commands.train import _sized

    declared = load_config("tiny")
    shaped = dataclasses.replace(_on(declared, (96, 128), 2), train=dataclasses.replace(
        declared.train, workdir=str(tmp_path / "old")))
    old = dataclasses.asdict(shaped)
    del old["model"]["frame_tokens"]
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "config.json").write_text(json.dumps(old))
    kept = _sized(shaped, declared, frozenset())
    assert (kept.model.frame_tokens, kept.model.patch_size, kept.data.batch_size) == (None, 8, 32)
    fresh = _sized(dataclasses.replace(shaped, train=dataclasses.replace(shaped.train, workdir=str(tmp_path / "new"))),
                   declared, frozenset())
    assert (fresh.model.frame_tokens, fresh.model.patch_size, fresh.data.batch_size) == (12, 32, 8)


def test_an_image_size_no_patch_can_fit_is_one_line_naming_the_fix():
    """97 x 128 has no common divisor but 1: thousands of 1-pixel tokens a frame would be a silent cost."""
    from sc3_jax.core.errors import UserError

    declared = load_config("tiny")
    with pytest.raises(UserError, match="--image-size H W"):
        sizing.size_from_data(_on(declared, (97, 128), 2), declared)
