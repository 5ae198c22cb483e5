"""The learning rate decays to (near) zero by a run's last step, whatever its length and warm-up; a warm-up that would
swallow the run is refused in one line (a run once ended at the top of its warm-up: warmup_steps = steps = 150)."""
import dataclasses

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.core.config import TrainConfig
from sc3_jax.core.errors import UserError
from sc3_jax.train.train import check_schedule, lr_schedule, warmup_of


@settings(max_examples=60, deadline=None)
@given(steps=st.integers(1, 50_000), warmup=st.one_of(st.none(), st.integers(1, 50_000)), lr=st.floats(1e-6, 1e-1))
def test_the_rate_rises_over_the_warm_up_and_ends_near_zero_at_the_last_step(steps, warmup, lr):
    t = TrainConfig(steps=steps, warmup_steps=warmup, lr=lr)
    if warmup_of(t) >= steps:
        with pytest.raises(UserError, match="never decay"):
            lr_schedule(t)
        return
    f = lr_schedule(t)
    w = warmup_of(t)
    assert float(f(0)) == (0.0 if w else pytest.approx(lr, rel=1e-5))
    assert float(f(w)) == pytest.approx(lr, rel=1e-5)  # the peak, at the warm-up's end
    last = float(f(steps - 1))  # the last step's update
    tail = steps - w  # the decay's length: one step of it is at most pi^2/4 / tail^2 of the peak from the bottom
    assert last <= lr * (min(1.0, 2.5 / tail ** 2) + 1e-6)  # + float32 rounding
    assert float(f(steps)) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("steps", [1, 2, 30, 150, 400, 6000, 100_000])
def test_the_default_warm_up_is_a_short_fraction_of_any_run(steps):
    w = warmup_of(TrainConfig(steps=steps))
    assert 0 <= w <= 100 and w < steps and w <= steps // 10
    lr_schedule(TrainConfig(steps=steps))  # never refused: a 1-step smoke run updates at the peak rate


def test_a_warm_up_as_long_as_the_run_is_one_line_that_names_a_fix():
    t = TrainConfig(steps=150, warmup_steps=150)
    with pytest.raises(UserError) as e:
        check_schedule(t)
    assert "--train.warmup-steps 5" in str(e.value) and "\n" not in str(e.value)
    check_schedule(dataclasses.replace(t, warmup_steps=149))  # one decaying step: allowed


def test_a_continuation_from_an_export_warms_up_again_and_decays_to_zero():
    # init_from starts a fresh optimizer at step 0: the same schedule, on the continuation's own length
    t = TrainConfig(steps=400, lr=1e-3, init_from="some/export")
    f = lr_schedule(t)
    assert warmup_of(t) == 13 and float(f(0)) == 0.0 and float(f(13)) == pytest.approx(1e-3)
    assert float(f(399)) < 1e-3 * 1e-4
