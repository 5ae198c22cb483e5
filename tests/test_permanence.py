"""Object permanence (measures/permanence.py): how much of the objects imagined frames keep against real ones, in
the sweep report (a synthetic store whose imagined objects vanish reads low, one whose objects stay reads 1) and
with the simulated benchmark's measure (its objects' colours, shading-invariant)."""
import numpy as np
import pytest

from sc3_jax.benchmarks.bussing.hooks import object_pixels
from sc3_jax.measures import permanence
from sc3_jax.evaluation import report_bench
from sc3_jax.evaluation.results import ResultsStore, rollout_id

TABLE = (205, 180, 145)  # beige, as the benchmark's table
RED = (230, 31, 31)  # the benchmark's red cup, lit
V, T, H, W, STRIDE = 3, 25, 16, 16, 2  # real frames at the simulator's rate; the model reads every 2nd


def _frames(n: int, object_until: int | None = None, shade: float = 1.0) -> np.ndarray:
    """[V, n, H, W, 3]: the table with a 3x3 red object in every view (until frame ``object_until``)."""
    f = np.empty((V, n, H, W, 3), np.uint8)
    f[:] = TABLE
    stop = n if object_until is None else object_until
    f[:, :stop, 5:8, 5:8] = (np.array(RED) * shade).astype(np.uint8)
    return f


def test_pixels_of_counts_an_objects_colour_in_light_and_shade_and_not_the_table():
    lit, shaded = _frames(1), _frames(1, shade=0.6)
    assert object_pixels(lit)[0, 0] == pytest.approx(9 / (H * W))
    assert object_pixels(shaded)[0, 0] == pytest.approx(9 / (H * W))  # chromaticity: the same red in shade
    assert object_pixels(_frames(1, object_until=0)).max() == 0  # the table alone


def _store(tmp_path, vanish: bool) -> tuple[ResultsStore, dict, dict]:
    cfg = {"episode_seconds": 12.0, "world_model": str(tmp_path / "no_model")}
    store = ResultsStore(tmp_path / ("vanish" if vanish else "stay"), config=cfg)
    online = {}
    for seed in (1, 2, 3):
        real = _frames(T)
        imagined = _frames(13, object_until=1 if vanish else None)  # vanish: only the last context frame has it
        rec = {"id": rollout_id("p", seed, "online"), "mode": "online", "policy": "p", "seed": seed,
               "stride": STRIDE, "frames_per_chunk": 4, "num_chunks": 3}
        store.save_arrays(rollout_id("p", seed, "real"), frames=real)
        store.save_arrays(rec["id"], frames=imagined)
        store.append([rec, {"id": rollout_id("p", seed, "real"), "mode": "real", "policy": "p", "seed": seed}])
        online["p", seed] = rec
    return store, cfg, online


@pytest.mark.parametrize("vanish", [True, False])
def test_the_report_reads_vanishing_objects_low_and_kept_ones_high(tmp_path, vanish):
    store, cfg, online = _store(tmp_path, vanish)
    kept = report_bench._permanence(store, cfg, online, object_pixels, draws=200, seed=0)
    # 12 imagined frames over 12 s: 1 frame a second; every time up to 12 s is read, over the 3 conditions
    assert list(kept) == ["1 s", "2 s", "4 s", "6 s", "12 s"]
    for label, e in kept.items():
        assert e["rollouts"] == 3 and set(e["kept"]) == {"all views", "view 0", "view 1", "view 2"}
        v = e["kept"]["all views"]
        if vanish:
            assert v["value"] == 0 and v["hi"] == 0, label
        else:
            assert v["value"] == pytest.approx(1) and v["lo"] == pytest.approx(1), label


def test_a_store_without_frames_or_a_horizon_has_no_permanence(tmp_path):
    store, cfg, online = _store(tmp_path, vanish=False)
    assert report_bench._permanence(store, {**cfg, "episode_seconds": None}, online, object_pixels, 10, 0) is None
    for p in (store.root / "rollouts").rglob("*.npz"):
        p.unlink()
    assert report_bench._permanence(store, cfg, online, object_pixels, 10, 0) is None


def test_summary_counts_only_rollouts_that_reach_a_time_and_intervals_bracket_the_value():
    rng = np.random.default_rng(0)
    re = rng.uniform(0.5, 1.0, (20, 2, 3))
    im = re * rng.uniform(0.3, 0.7, (20, 2, 3))
    im[:5, :, 2] = re[:5, :, 2] = np.nan  # five rollouts end before the third time
    out = permanence.summary(im, re, {"a": 0, "b": 2, "past": 5}, ["x", "y"], draws=300)
    assert list(out) == ["a", "b"] and out["a"]["rollouts"] == 20 and out["b"]["rollouts"] == 15
    for e in out.values():
        for c in e["kept"].values():
            assert 0.3 < c["lo"] <= c["value"] <= c["hi"] < 0.7
