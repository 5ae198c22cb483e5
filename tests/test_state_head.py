"""The learned robot state (sc3_jax/rollout/state_head.py): a two-link arm driven by end-effector deltas records its
joint angles, so the state is not the integral of the actions; the head learns it from the episodes and, unrolled over
held-out episodes as a rollout unrolls it, beats holding the first state and integrating the commands by half."""
import numpy as np
import pytest

from sc3_jax.rollout import state_head
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore

L1, L2, SIZE = 1.0, 0.8, 16
SPACE = ActionSpace("velocity", 3, ("dx", "dy", "gripper"), targets=(2,))


def _ee(q):
    return np.array([L1 * np.cos(q[0]) + L2 * np.cos(q[0] + q[1]), L1 * np.sin(q[0]) + L2 * np.sin(q[0] + q[1])])


def _draw(q) -> np.ndarray:
    """A 16 x 16 frame: the elbow grey, the hand white (pixel = 8 + 3.5 * position)."""
    img = np.zeros((SIZE, SIZE, 3), np.uint8)
    elbow = np.array([L1 * np.cos(q[0]), L1 * np.sin(q[0])])
    for p, v in ((elbow, 120), (_ee(q), 255)):
        r, c = np.clip(np.round(8 + 3.5 * p).astype(int), 1, SIZE - 2)
        img[r - 1:r + 2, c - 1:c + 2] = v
    return img


def arm_episode(rng, eid: str, length: int = 40) -> Episode:
    """End-effector deltas (and a gripper target) commanded; the joints follow by damped least squares; the state
    is (joint 1, joint 2, the gripper's opening, which lags its target)."""
    q, g = rng.uniform([0.3, 0.6], [1.2, 1.8]), 0.0
    acts, states, frames = [], [], []
    goal = rng.uniform(-0.3, 0.3, 2)
    for t in range(length):
        states.append([q[0], q[1], g])
        frames.append(_draw(q))
        d = np.clip(0.15 * goal + rng.normal(0, 0.03, 2), -0.1, 0.1)
        if t % 10 == 0:
            goal = rng.uniform(-0.3, 0.3, 2)
        target = float(rng.random() < 0.5) if t % 8 == 0 else (acts[-1][2] if acts else 0.0)
        acts.append([d[0], d[1], target])
        s1, c1, s12, c12 = np.sin(q[0]), np.cos(q[0]), np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
        jac = np.array([[-L1 * s1 - L2 * s12, -L2 * s12], [L1 * c1 + L2 * c12, L2 * c12]])
        q = q + jac.T @ np.linalg.solve(jac @ jac.T + 0.01 * np.eye(2), d)
        g = g + 0.5 * (target - g)
    return Episode(eid, {"front": np.stack(frames)}, np.asarray(acts, np.float32), None,
                   state=np.asarray(states, np.float32))


def arm_store(root, episodes: int, seed: int) -> EpisodeStore:
    store = EpisodeStore(root, ["front"], fps=10.0, image_size=(SIZE, SIZE), create=True, action_space=SPACE,
                         state_dim=3, state_names=["joint1", "joint2", "gripper"], has_pose=False)
    rng = np.random.default_rng(seed)
    for i in range(episodes):
        store.write(arm_episode(rng, f"ep{i:06d}"))
    return store


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("arm")
    return arm_store(root / "train", 24, 0), arm_store(root / "heldout", 6, 1)


def test_the_learned_state_halves_the_error_of_holding_or_integrating(stores):
    train, held = stores
    seqs = state_head.transitions(train.root, ["front"], 1, SPACE)
    head, fitted = state_head.fit(seqs, state_head.FitConfig(steps=600))
    test = state_head.transitions(held.root, ["front"], 1, SPACE)
    err = state_head.errors(head, test)
    std = np.asarray(head["state_std"])
    se, n = 0.0, 0
    for states, acts, _ in test:  # integrating the commands onto the matching dimensions, the gripper's target
        pred = SPACE.integrate(states[0], acts)[1:]
        se, n = se + float(np.sum(np.square((pred - states[1:]) / std))), n + states[1:].size
    integrate = float(np.sqrt(se / n))
    assert err["head"] < 0.5 * err["hold"] and err["head"] < 0.5 * integrate, (err, integrate, fitted)


def test_a_store_without_a_state_has_nothing_to_learn(tmp_path):
    from sc3_jax.core.errors import UserError

    store = EpisodeStore(tmp_path / "s", ["front"], fps=10.0, image_size=(SIZE, SIZE), create=True,
                         action_space=SPACE, has_pose=False)
    ep = arm_episode(np.random.default_rng(0), "ep000000", 5)
    store.write(Episode(ep.episode_id, ep.frames, ep.actions, None))
    with pytest.raises(UserError, match="records no robot state"):
        state_head.transitions(store.root, ["front"], 1, SPACE)
