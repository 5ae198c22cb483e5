"""A tiny deterministic multi-view pushing world (pure numpy) for tests and the first demo.

World (metres, z up): a 0.6 m x 0.6 m table centred at the origin with walls, 1-3 flat square blocks and an
"end effector": a square plate at height z carrying a lamp that shines along its tool axis, with a yaw marker and
two gripper fingers. Every action dimension is visible:

- dx, dy   move the plate (clipped at the walls) and push blocks it touches while low (z < ``PUSH_HEIGHT``);
- dz       the plate's height: perspective size/position in both third-person views, lamp cone size, wrist zoom;
- rx, ry   tilt the tool axis: the lamp spot on the table moves, the plate colour changes, the wrist view shifts;
- rz       yaw: the plate's marker and fingers rotate, the wrist camera rotates;
- gripper  target opening (metres, 0..0.08); the real width follows at a limited rate: the finger spacing and the
           plate colour change, and the wrist camera sees the fingers open/close.

Cameras: ``left`` is a top-down pinhole camera (height ``CAM_HEIGHT``); ``right`` is a mirrored, sheared oblique
view with its own colouring (raised things appear displaced); ``wrist`` moves with the end effector (centred on the
tool axis' intersection with the table, rotating with yaw, zooming with height) over a textured table, so almost
every wrist pixel changes when the effector moves. The lamp lights a large part of the table in every view, so a
large share of the pixels of each view responds to the actions (see ``pixel_change_fraction``).

``actions[t]`` is applied after frame ``t``: (dx, dy, dz [m], axis-angle delta rx, ry, rz [rad, world frame:
``R_{t+1} = R(a) R_t``], gripper target width [m]). ``ee_pose[t]`` = (x, y, z, rotvec(R_t), gripper width) at frame
``t``; pseudo-actions from consecutive poses match the actions up to wall clipping and the gripper's rate limit.
"""
from __future__ import annotations

import numpy as np

from sc3_jax.data import rotations
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.core.errors import UserError

VIEWS = ("left", "right", "wrist")
FPS = 20
PROMPT = "push the blocks"

HALF_TABLE = 0.3  # table is [-0.3, 0.3]^2
AGENT_HALF = 0.085  # plate half size
XY_LIMIT = 0.24  # plate centre stays within [-0.24, 0.24]
Z_RANGE = (0.02, 0.20)
GRIPPER_MAX = 0.08
GRIPPER_RATE = 0.01  # max width change per step
PUSH_HEIGHT = 0.12
CAM_HEIGHT = 0.7  # left camera above the table centre
LAMP_OFFSET = 0.15  # lamp height above the plate
VIEW_SPAN = 0.33  # third-person views show [-0.33, 0.33] (walls visible at the border)
RIGHT_DISPLACE = np.array([0.55, -0.35])  # right view: a point at height z appears shifted by z * this (table units)
SUPERSAMPLE_GRID = 64  # render on a fine grid of at least this many samples per side, then area-average

_BLOCK_COLOURS = np.array([[0.85, 0.2, 0.15], [0.15, 0.35, 0.9], [0.95, 0.8, 0.1], [0.2, 0.75, 0.3]])


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth table texture in [0, 1] (period ~0.1 m), a pure function of table position."""
    return 0.5 + 0.22 * np.sin(61.0 * x + 1.3) * np.sin(53.0 * y) + 0.18 * np.sin(37.0 * x - 45.0 * y + 0.7)


def _pool(img: np.ndarray, ss: int) -> np.ndarray:
    h, w = img.shape[0] // ss, img.shape[1] // ss
    return img.reshape(h, ss, w, ss, -1).mean(axis=(1, 3))


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


class SyntheticEnv:
    """``reset() -> obs``, ``step(action) -> obs``, ``render() -> {view: uint8 [H, W, 3]}``, ``ee_pose() -> [7]``."""

    views = VIEWS

    def __init__(self, image_size: tuple[int, int] = (16, 16), seed: int | np.random.SeedSequence = 0,
                 num_objects: int | None = None):
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self._seed = seed
        self._num_objects = num_objects
        h, w = self.image_size
        self._ss = ss = max(1, -(-SUPERSAMPLE_GRID // max(h, w)))
        # normalised fine-pixel coordinates u (right), v (down) in [-1, 1]
        v, u = np.meshgrid((np.arange(h * ss) + 0.5) / (h * ss) * 2 - 1, (np.arange(w * ss) + 0.5) / (w * ss) * 2 - 1,
                           indexing="ij")
        self._u, self._v = u, v
        # table coordinates seen by each static camera (for things at height 0)
        self._table = {
            "left": (VIEW_SPAN * u, -VIEW_SPAN * v),
            "right": (VIEW_SPAN * (0.85 * v + 0.25 * u), VIEW_SPAN * u),  # mirrored + sheared oblique view
        }
        self._floor = {}
        for view, (x, y) in self._table.items():
            tex = _texture(x, y)
            if view == "left":
                col = np.stack([0.55 + 0.35 * tex, 0.45 + 0.3 * tex, 0.35 + 0.2 * tex], -1)
            else:
                col = np.stack([0.25 + 0.25 * (1 - tex), 0.4 + 0.3 * (1 - tex), 0.55 + 0.35 * tex], -1)
            wall = (np.abs(x) > HALF_TABLE) | (np.abs(y) > HALF_TABLE)
            col[wall] = (0.15, 0.15, 0.2) if view == "left" else (0.3, 0.1, 0.15)
            self._floor[view] = (col, wall)
        self.reset()

    # -- state ----------------------------------------------------------------------------------------------------
    def reset(self, seed: int | np.random.SeedSequence | None = None) -> dict[str, np.ndarray]:
        if seed is not None:
            self._seed = seed
        rng = np.random.default_rng(self._seed)
        self.rng = rng
        n = self._num_objects if self._num_objects is not None else int(rng.integers(1, 4))
        self.pos = np.array([*rng.uniform(-0.15, 0.15, 2), rng.uniform(0.05, 0.15)])
        self.rot = rotations.rotvec_to_matrix(np.array([*rng.normal(0, 0.15, 2), rng.uniform(-np.pi, np.pi)]))
        self.width = float(rng.uniform(0.0, GRIPPER_MAX))
        self.block_half = rng.uniform(0.05, 0.07, n)
        self.blocks = np.zeros((n, 2))
        for i in range(n):  # away from the plate and each other where possible
            for _ in range(50):
                b = rng.uniform(-HALF_TABLE + self.block_half[i], HALF_TABLE - self.block_half[i], 2)
                far_agent = np.max(np.abs(b - self.pos[:2])) > AGENT_HALF + self.block_half[i] + 0.02
                far_blocks = all(np.max(np.abs(b - self.blocks[j])) > self.block_half[i] + self.block_half[j]
                                 for j in range(i))
                if far_agent and far_blocks:
                    break
            self.blocks[i] = b
        self.block_colour = _BLOCK_COLOURS[rng.permutation(len(_BLOCK_COLOURS))[:n]]
        return self.render()

    def ee_pose(self) -> np.ndarray:
        return np.concatenate([self.pos, rotations.matrix_to_rotvec(self.rot), [self.width]]).astype(np.float32)

    def step(self, action: np.ndarray) -> dict[str, np.ndarray]:
        a = np.asarray(action, np.float64)
        if a.shape != (7,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be a finite [7] vector, got {a!r}")
        lo = np.array([-XY_LIMIT, -XY_LIMIT, Z_RANGE[0]])
        hi = np.array([XY_LIMIT, XY_LIMIT, Z_RANGE[1]])
        self.pos = np.clip(self.pos + a[:3], lo, hi)
        self.rot = rotations.rotvec_to_matrix(a[3:6]) @ self.rot
        self.rot = _orthonormalise(self.rot)
        target = float(np.clip(a[6], 0.0, GRIPPER_MAX))
        self.width += float(np.clip(target - self.width, -GRIPPER_RATE, GRIPPER_RATE))
        if self.pos[2] < PUSH_HEIGHT:
            self._push()
        return self.render()

    def _push(self) -> None:
        """Axis-aligned square contact: move each overlapping block out along the axis of least penetration."""
        for i in range(len(self.blocks)):
            d = self.blocks[i] - self.pos[:2]
            reach = AGENT_HALF + self.block_half[i]
            pen = reach - np.abs(d)
            if np.all(pen > 0):
                k = int(np.argmin(pen))
                self.blocks[i, k] += np.sign(d[k] if d[k] != 0 else 1.0) * pen[k]
                lim = HALF_TABLE - self.block_half[i]
                self.blocks[i] = np.clip(self.blocks[i], -lim, lim)

    # -- rendering ------------------------------------------------------------------------------------------------
    def _geometry(self):
        tool = -self.rot[:, 2]  # tool axis (points down at identity)
        heading = self.rot[:2, 0]
        yaw = float(np.arctan2(heading[1], heading[0])) if np.linalg.norm(heading) > 1e-6 else 0.0
        lamp_h = self.pos[2] + LAMP_OFFSET
        spot = self.pos[:2] + lamp_h * tool[:2] / max(-tool[2], 0.4)
        radius = 0.06 + 0.7 * lamp_h
        return tool, yaw, spot, radius

    def _light(self, x, y, spot, radius):
        d = np.sqrt((x - spot[0]) ** 2 + (y - spot[1]) ** 2)
        return 0.35 + 0.9 * np.clip(1.0 - d / radius, 0.0, 1.0)

    def _draw_blocks(self, img, x, y, view):
        for i in range(len(self.blocks)):
            m = (np.abs(x - self.blocks[i, 0]) < self.block_half[i]) & (np.abs(y - self.blocks[i, 1]) < self.block_half[i])
            c = self.block_colour[i] if view != "right" else self.block_colour[i][[2, 0, 1]]
            img[m] = c

    def _draw_agent(self, img, px, py, yaw, tool, view):
        """(px, py): plate-plane coordinates of each fine pixel."""
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = px - self.pos[0], py - self.pos[1]
        a, b = c * dx + s * dy, -s * dx + c * dy  # plate frame: a forward (heading), b left
        body = (np.abs(a) < AGENT_HALF) & (np.abs(b) < AGENT_HALF)
        marker = body & (a > 0.35 * AGENT_HALF) & (np.abs(b) < 0.5 * AGENT_HALF)
        g = 0.5 * self.width + 0.008
        fingers = (a > AGENT_HALF - 0.01) & (a < AGENT_HALF + 0.045) & (np.abs(b) > g) & (np.abs(b) < g + 0.03)
        w = self.width / GRIPPER_MAX
        colour = np.array([0.5 + 0.45 * tool[0], 0.5 + 0.45 * tool[1], 0.25 + 0.6 * w])
        if view == "right":
            colour = colour[[1, 2, 0]] * 0.9
        img[body] = np.clip(colour, 0, 1)
        img[marker] = (0.05, 0.05, 0.05) if view == "left" else (0.95, 0.95, 0.95)
        img[fingers] = (0.9, 0.9 * w, 0.9 * (1 - w))

    def render(self) -> dict[str, np.ndarray]:
        tool, yaw, spot, radius = self._geometry()
        out = {}
        z = self.pos[2]
        for view in ("left", "right"):
            x, y = self._table[view]
            col, wall = self._floor[view]
            img = col.copy()
            self._draw_blocks(img, x, y, view)
            img *= np.where(wall, 1.0, self._light(x, y, spot, radius))[..., None]
            if view == "left":  # pinhole camera above the origin: the plate at height z is magnified
                scale = (CAM_HEIGHT - z) / CAM_HEIGHT
                px, py = x * scale, y * scale
            else:  # oblique: a raised plate appears displaced
                px, py = x - z * RIGHT_DISPLACE[0], y - z * RIGHT_DISPLACE[1]
            self._draw_agent(img, px, py, yaw, tool, view)
            out[view] = _to_uint8(_pool(img, self._ss))
        # wrist: looks along the tool axis, rotates with yaw, sees more of the table when higher
        span = 0.06 + 0.5 * z
        c, s = np.cos(yaw), np.sin(yaw)
        fu, fv = span * self._u, -span * self._v  # camera frame: up in the image = forward (heading)
        centre = self.pos[:2] + z * tool[:2] / max(-tool[2], 0.4)
        x = centre[0] + c * fv - s * fu
        y = centre[1] + s * fv + c * fu
        tex = _texture(x, y)
        img = np.stack([0.3 + 0.6 * tex, 0.55 + 0.35 * tex, 0.5 - 0.3 * tex], -1)
        wall = (np.abs(x) > HALF_TABLE) | (np.abs(y) > HALF_TABLE)
        img[wall] = (0.1, 0.1, 0.12)
        self._draw_blocks(img, x, y, "wrist")
        img *= np.where(wall, 1.0, self._light(x, y, spot, radius))[..., None]
        w = self.width / GRIPPER_MAX
        g = 0.12 + 0.55 * w
        fingers = (self._v < -0.45) & (np.abs(self._u) > g) & (np.abs(self._u) < g + 0.3)
        img[fingers] = (0.85, 0.85 * w, 0.3)
        out["wrist"] = _to_uint8(_pool(np.clip(img, 0, 1), self._ss))
        return out


def _orthonormalise(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


class RandomExplorer:
    """Smooth random actions in physical units: the plate heads for targets (often a block, to push it) with
    Ornstein-Uhlenbeck noise on every dimension; yaw/tilt rates are OU with a weak pull back to upright; the gripper
    target is piecewise constant."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.vel = np.zeros(3)
        self.ang = np.zeros(3)
        self.target = np.zeros(3)
        self.steps_left = 0
        self.grip_target = GRIPPER_MAX
        self.grip_left = 0

    def __call__(self, env: SyntheticEnv) -> np.ndarray:
        rng = self.rng
        if self.steps_left <= 0:
            self.steps_left = int(rng.integers(10, 35))
            if len(env.blocks) and rng.random() < 0.6:  # go through a block to push it
                i = int(rng.integers(len(env.blocks)))
                direction = env.blocks[i] - env.pos[:2]
                direction /= max(np.linalg.norm(direction), 1e-6)
                xy = env.blocks[i] + 0.1 * direction
                zt = rng.uniform(Z_RANGE[0], 0.08)
            else:
                xy = rng.uniform(-XY_LIMIT, XY_LIMIT, 2)
                zt = rng.uniform(*Z_RANGE)
            self.target = np.array([*xy, zt])
        self.steps_left -= 1
        want = np.clip(0.25 * (self.target - env.pos), -0.018, 0.018)
        self.vel = 0.6 * self.vel + 0.4 * want + rng.normal(0, [0.004, 0.004, 0.002])
        delta = np.clip(self.vel, -0.025, 0.025)
        current = rotations.matrix_to_rotvec(env.rot)
        tilt_pull = -0.04 * np.array([current[0], current[1], 0.0])
        self.ang = 0.85 * self.ang + rng.normal(0, [0.012, 0.012, 0.025]) + tilt_pull
        self.ang = np.clip(self.ang, -0.12, 0.12)
        if self.grip_left <= 0:
            self.grip_left = int(rng.integers(8, 30))
            r = rng.random()
            self.grip_target = 0.0 if r < 0.35 else GRIPPER_MAX if r < 0.7 else float(rng.uniform(0, GRIPPER_MAX))
        self.grip_left -= 1
        return np.array([*delta, *self.ang, self.grip_target], np.float64)


def rollout(image_size=(16, 16), length: int = 80, seed=0, num_objects: int | None = None,
            actions: np.ndarray | None = None, episode_id: str = "episode") -> Episode:
    """One episode of ``length`` frames. ``actions`` (optional [length, 7]) replaces the random explorer.
    The last action (after the last frame) is recorded but has no visible effect."""
    ss = np.random.SeedSequence(seed) if not isinstance(seed, np.random.SeedSequence) else seed
    env_seed, policy_seed = ss.spawn(2)
    env = SyntheticEnv(image_size, env_seed, num_objects)
    policy = RandomExplorer(np.random.default_rng(policy_seed))
    frames = {v: np.zeros((length, *env.image_size, 3), np.uint8) for v in VIEWS}
    acts = np.zeros((length, 7), np.float32)
    poses = np.zeros((length, 7), np.float32)
    obs = env.render()
    for t in range(length):
        for v in VIEWS:
            frames[v][t] = obs[v]
        poses[t] = env.ee_pose()
        a = policy(env) if actions is None else np.asarray(actions[t], np.float64)
        acts[t] = a
        if t + 1 < length:
            obs = env.step(acts[t].astype(np.float64))
    return Episode(episode_id, frames, acts, poses, PROMPT,
                   {"source": "synthetic", "num_objects": int(len(env.blocks))})


def episode_id(i: int) -> str:
    return f"ep{i:06d}"


def generate(root, num_episodes: int, length: int = 80, image_size=(16, 16), seed: int = 0,
             progress: bool = True) -> EpisodeStore:
    """Write ``num_episodes`` episodes to ``root`` (resumable: episodes already there are skipped). Episode ``i`` is
    a deterministic function of ``(seed, i)`` (and length/image size)."""
    store = EpisodeStore(root, views=list(VIEWS), fps=FPS, image_size=tuple(image_size), create=True)
    if tuple(store.image_size) != tuple(image_size):
        raise UserError(f"{root}: dataset has image size {tuple(store.image_size)}, asked for {tuple(image_size)} "
                        "(another config's data): use another --out, or the config it was made with")
    todo = [i for i in range(num_episodes) if episode_id(i) not in store]
    it = todo
    if progress and todo:
        from tqdm import tqdm
        it = tqdm(todo, desc="synthetic episodes", unit="ep")
    for i in it:
        ep = rollout(image_size, length, np.random.SeedSequence([seed, i]), episode_id=episode_id(i))
        store.write(ep)
    return store


def pixel_change_fraction(frames: np.ndarray, threshold: int = 4) -> float:
    """Mean over consecutive frame pairs of the fraction of pixels whose largest channel change exceeds
    ``threshold`` (uint8 levels). ``frames``: uint8 [T, H, W, 3]."""
    f = np.asarray(frames).astype(np.int16)
    if f.shape[0] < 2:
        return 0.0
    diff = np.abs(f[1:] - f[:-1]).max(axis=-1)
    return float(np.mean(diff > threshold))


def view_change_fractions(ep: Episode, threshold: int = 4) -> dict[str, float]:
    """``pixel_change_fraction`` per view of one episode."""
    return {v: pixel_change_fraction(f, threshold) for v, f in ep.frames.items()}
