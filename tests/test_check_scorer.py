"""`sc3 check-scorer --data STORE --scorer SPEC`: a scorer run on a store's labelled real episodes (their frames and state,
as a sweep hands it imagined rollouts) and compared with the labels, with a Wilson interval; bad input is one line
before anything is scored."""
import json

import numpy as np
import pytest

from sc3_jax.cli import main
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore

# (brightness of the episode's frames, its label): the scorer below says done when the last frame is bright, so it
# is right on the first four and wrong on the last two (one false done, one missed)
EPISODES = [(200, True), (10, False), (220, True), (0, False), (250, False), (5, True)]


def bright(view):
    """A scorer: done when the first view's last frame is bright; it reads the state too (must be handed one)."""
    assert view.state is not None and view.state.shape == (3, 2)
    return {"success": bool(view.frames[0, -1].mean() > 100)}


def _store(root):
    st = EpisodeStore(root, views=["cam"], fps=10, image_size=(8, 8), create=True,
                      action_space=ActionSpace("absolute", 2), has_pose=False, state_dim=2)
    for i, (level, label) in enumerate(EPISODES):
        st.write(Episode(f"e{i}", {"cam": np.full((3, 8, 8, 3), level, np.uint8)}, np.zeros((3, 2), np.float32),
                         None, meta={"labels": {"success": label}}, state=np.zeros((3, 2), np.float32)))
    return root


def test_check_scorer_counts_agreement_false_done_and_missed_with_an_interval(tmp_path, capsys):
    store = _store(tmp_path / "s")
    out = tmp_path / "check.json"
    assert main(["check-scorer", "--data", str(store), "--scorer", f"{__name__}:bright", "--out", str(out),
                 "--no-progress"]) == 0
    r = json.loads(out.read_text())
    assert (r["n"], r["scorer_done"], r["labels_done"], r["false_done"], r["missed"]) == (6, 3, 3, 1, 1)
    assert r["agreement"] == pytest.approx(4 / 6) and r["disagree"] == ["e4", "e5"]
    assert r["interval"]["lo"] < 4 / 6 < r["interval"]["hi"]
    assert "agrees with the labels on 0.667" in capsys.readouterr().out


def test_check_scorer_refuses_a_missing_criterion_a_folder_as_out_and_a_bad_scorer_in_one_line(tmp_path, capsys):
    store = _store(tmp_path / "s")
    for extra, said in ((["--scorer", f"{__name__}:bright", "--criterion", "placed"], "no label 'placed'"),
                        (["--scorer", f"{__name__}:bright", "--out", str(tmp_path)], "not a file that can be written"),
                        (["--scorer", "os:getcwd"], "not one RolloutView")):
        assert main(["check-scorer", "--data", str(store), "--no-progress", *extra]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], err


def test_check_scorer_names_its_own_option_for_a_folder_that_is_no_store(tmp_path, capsys):
    assert main(["check-scorer", "--data", str(tmp_path), "--scorer", f"{__name__}:bright", "--no-progress"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--data" in err[0] and "no dataset.json" in err[0] and "--real" not in err[0], err
