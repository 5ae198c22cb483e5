"""Checks shared by the training-switch tests: a stopped and resumed run logs what one uninterrupted run logs; a
switch left off trains bit-identically."""
from sc3_jax.train import train


def assert_resumed_like_straight(straight, resumed, metric: str, steps=(1, 2, 3, 4)) -> None:
    """Every logged metric of every step equal (but the wall-clock rate); ``metric``: one the feature under test
    logs, so a run without it cannot pass."""
    a, b = train.read_metrics(straight), train.read_metrics(resumed)
    assert sorted(a) == sorted(b) == list(steps)
    for step in a:
        assert metric in a[step]
        for k in a[step]:
            if k != "steps_per_s":
                assert b[step][k] == a[step][k], (step, k)


def assert_same_training(a, b) -> None:
    """Two (params, per-step metrics) of the same steps bit-identical: a switch that is off changes nothing."""
    import jax
    import numpy as np

    (params, rows), (ref_params, ref_rows) = a, b
    for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)):
        np.testing.assert_array_equal(x, y)
    for row, ref in zip(rows, ref_rows):
        assert row.keys() == ref.keys()
        for k in row:
            np.testing.assert_array_equal(row[k], ref[k], err_msg=k)
