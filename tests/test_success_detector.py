"""`sc3 train-detector`: a success detector learnt from an episode store's own labels, then used as a sweep's scorer
(`--scorer detector:DIR`). The store here: 20 episodes of a 16x16 camera, a white square appears in the last frames
of those labelled done; the detector must find it in held-out episodes."""
import json

import numpy as np
import pytest

from sc3_jax.cli import main
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.evaluation.scorers import RolloutView, load_outcome_scorer
from sc3_jax.evaluation.success_detector import decide


def _store(root, n=20, labels=True):
    st = EpisodeStore(root, views=["cam"], fps=10, image_size=(16, 16), create=True,
                      action_space=ActionSpace("absolute", 2), has_pose=False)
    rng = np.random.default_rng(0)
    for i in range(n):
        done = i % 2 == 0
        t = 24
        frames = rng.integers(0, 60, (t, 16, 16, 3)).astype(np.uint8)
        if done:
            frames[-3:, 5:10, 5:10] = 255  # the task's final state: the square is there
        meta = {"labels": {"success": done}} if labels else {}
        st.write(Episode(f"ep{i:03d}", {"cam": frames}, np.zeros((t, 2), np.float32), None, "", meta))
    return st


def test_decide_needs_consecutive_frames_above_the_threshold():
    assert decide(np.array([0.1, 0.9, 0.2, 0.9]), 0.5, 2) is False
    assert decide(np.array([0.1, 0.9, 0.9, 0.2]), 0.5, 2) is True
    assert decide(np.array([0.9]), 0.5, 2) is True  # fewer frames than asked: all of them
    assert decide(np.array([]), 0.5, 2) is False


def test_the_detector_learns_the_labels_and_scores_rollouts(tmp_path, capsys):
    st = _store(tmp_path / "store")
    assert main(["train-detector", "--data", str(st.root), "--out", str(tmp_path / "det"), "--steps", "150",
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "held out (2 episodes)" in out and "--scorer detector:" in out
    info = json.loads((tmp_path / "det" / "detector.json").read_text())
    assert info["heldout"]["episode_agreement"] == 1.0 and info["views"] == ["cam"]
    scorer = load_outcome_scorer(f"detector:{tmp_path / 'det'}")
    done, not_done = st.load("ep018"), st.load("ep019")  # held out (the last tenth)
    view = lambda ep: RolloutView(ep.episode_id, np.asarray(ep.frames["cam"])[None])  # noqa: E731
    assert scorer(view(done)) == {"success": True} and scorer(view(not_done)) == {"success": False}


def test_a_store_without_labels_or_a_missing_detector_is_one_line(tmp_path, capsys):
    st = _store(tmp_path / "store", n=4, labels=False)
    assert main(["train-detector", "--data", str(st.root), "--out", str(tmp_path / "det"), "--steps", "2",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no episode has a boolean labels.success" in err and "\n" not in err
    from sc3_jax.core.errors import UserError
    with pytest.raises(UserError, match="no detector.json"):
        load_outcome_scorer(f"detector:{tmp_path / 'nothing'}")
