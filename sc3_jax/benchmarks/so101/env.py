"""The SO-101 pick-and-place environment: ``lerobot_env_so101/SO101PickPlace-v0`` behind a small reset / step / render
interface.

Observation (the simulator's own): ``agent_pos`` float32 [14] (5 joint positions, 5 joint velocities, the gripper
command mapped to [-1, 1] (-1 closed), the ``gripperframe`` site's xyz) and ``environment_state`` float32 [6] (block
centre xyz, goal xyz). Action float32 [4]: dx, dy, dz in [-1, 1], ``ACTION_SCALE`` metres each, moving the grasp point
between the jaws, and the gripper target in [0, 1] (1 open, 0 closed); actions are clipped to that box (the simulator
itself does not clip). 10 Hz control. An episode ends on success (the block was lifted, rests within 3 cm of the goal,
the jaw open) or when the block leaves the workspace.

Rendering is ours, not the simulator's: shadows and multisampling off, because on a software renderer (llvmpipe via
EGL) the scene's two shadow-casting lights and 8x multisampling cost ~1 s per 96x128 frame, against ~70 ms without
(the arm's meshes, ~320k triangles, are the rest); and the goal, which the simulator does not draw, is drawn as a green
disc of the success radius, so that frames show where the block must go.

Cameras (``CAMERAS``): the cameras a lab mounts on an SO-101 table, ``workspace`` (framing the arm, the block's and
the goal's sampling area, from the side: from the front the arm's home pose hangs over the table and hides the goal
in the first frames) and ``wrist`` (following the gripper, looking down past the jaws: the
block is large in it when the arm is over it), and the simulator's own ``front`` (the whole room from 0.8 m: at
96x128 the block is ~4 pixels wide, which is why the world model lost it). The two lab cameras are free MuJoCo
cameras set per frame, so the simulator's model is not edited; ``wrist`` tracks the ``gripperframe`` site's position
(its orientation stays fixed, as on a camera that does not roll with the wrist).
"""
from __future__ import annotations

import numpy as np

from sc3_jax.core.errors import UserError

ENV_ID = "lerobot_env_so101/SO101PickPlace-v0"
ACTION_SCALE = 0.025  # metres per unit of dx, dy, dz (the package's DEFAULT_ACTION_SCALE, which its controller uses)
ACTION_LOW = np.array([-1.0, -1.0, -1.0, 0.0], np.float32)
ACTION_HIGH = np.array([1.0, 1.0, 1.0, 1.0], np.float32)
ACTION_NAMES = ["dx", "dy", "dz", "gripper"]
JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
STATE_NAMES = [f"{j}.pos" for j in JOINTS] + [f"{j}.vel" for j in JOINTS] + ["gripper", "ee_x", "ee_y", "ee_z"]
ENV_STATE_NAMES = ["block_x", "block_y", "block_z", "goal_x", "goal_y", "goal_z"]
GOAL_RGBA = np.array([0.15, 0.75, 0.25, 1.0], np.float32)
BLOCK_RGBA = np.array([0.6, 0.3, 0.6, 1.0], np.float32)  # the package's "block" geom (tested against its model)
INSTALL = "pip install -e '.[so101]'"
VIEWS = ("workspace", "wrist")  # the benchmark's cameras (a lab's two); ("front",) is the simulator's room view
# free cameras: (look-at point or offset from the gripper site, distance m, azimuth deg, elevation deg)
CAMERAS = {"workspace": ((0.2, 0.0, 0.04), 0.45, 120.0, -55.0),
           "wrist": ((0.0, 0.0, -0.05), 0.18, 200.0, -65.0)}


def import_simulator():
    """The simulator's modules, or a one-line UserError saying how to install them."""
    try:
        import gymnasium
        import lerobot_env_so101  # noqa: F401  (registers the gym ids)
        import mujoco
        from lerobot_env_so101.mujoco_env import GymRenderingSpec
        from lerobot_env_so101.pick_place_env import PLACE_SUCCESS_DISTANCE
    except ImportError as e:
        raise UserError(f"the SO-101 benchmark needs the simulator lerobot_env_so101 ({e}): install the extra: "
                        f"{INSTALL}") from None
    return gymnasium, mujoco, GymRenderingSpec, PLACE_SUCCESS_DISTANCE


def check_views(views) -> None:
    """One line for a camera the benchmark does not render (before any simulator or worker starts)."""
    if not views or any(v not in CAMERAS and v != "front" for v in views):
        raise UserError(f"SO-101 views {list(views)}: choose from {['front', *CAMERAS]}")


class So101Env:
    """One SO-101 table. ``reset(seed)`` then ``step(action)``; ``render_views()`` is every camera of ``views``
    (``render()`` the first), cached until the next step (a policy and the recorder may both ask for a step's
    frames)."""

    state_dim = 14
    action_dim = 4

    def __init__(self, image_size: tuple[int, int] = (80, 80), goal_marker: bool = True,
                 views: tuple[str, ...] = VIEWS):
        check_views(views)
        gym, mujoco, spec, self._success_radius = import_simulator()
        self._mujoco = mujoco
        self.views = tuple(views)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        h, w = self.image_size
        # render_spec sizes the model's offscreen buffer; the simulator's own renderer is never built
        self._gym = gym.make(ENV_ID, render_mode="rgb_array", image_obs=False, random_block_position=True,
                             action_scale=ACTION_SCALE, render_spec=spec(height=h, width=w, camera_id="front"))
        self._env = self._gym.unwrapped
        model = self._env.model
        model.vis.quality.offsamples = 0
        model.light_castshadow[:] = 0
        self.goal_marker = goal_marker
        self._renderer = None
        self._frames: np.ndarray | None = None
        self.t = 0

    # -- properties ----------------------------------------------------------------------------------------------
    @property
    def control_hz(self) -> int:
        return int(round(1.0 / self._env.control_dt))

    @property
    def unwrapped(self):
        """The simulator's environment (``ik_point_pos``, ``goal_pos``, ``model``, ``data``)."""
        return self._env

    def block_pos(self) -> np.ndarray:
        return np.asarray(self._env.data.sensor("block_pos").data, np.float64).copy()

    def goal_pos(self) -> np.ndarray:
        return np.asarray(self._env.goal_pos, np.float64)

    # -- episode -------------------------------------------------------------------------------------------------
    def reset(self, seed: int) -> dict[str, np.ndarray]:
        """The initial condition of ``seed`` (block and goal positions; the arm at home): the same for a seed
        whatever ran before (the simulator resets all its state and reseeds its generator)."""
        obs, _ = self._gym.reset(seed=int(seed))
        self._frames, self.t = None, 0
        return obs

    def step(self, action) -> tuple[dict[str, np.ndarray], bool, bool]:
        """(observation, success, done) after ``action`` (clipped to the action box)."""
        a = np.clip(np.asarray(action, np.float32).reshape(4), ACTION_LOW, ACTION_HIGH)
        obs, _, terminated, truncated, info = self._gym.step(a)
        self._frames, self.t = None, self.t + 1
        return obs, bool(info["succeed"]), bool(terminated or truncated)

    def render(self) -> np.ndarray:
        """uint8 [H, W, 3]: the first view now."""
        return self.render_views()[0]

    def render_views(self) -> np.ndarray:
        """uint8 [V, H, W, 3]: every view now, in ``views`` order."""
        if self._frames is None:
            mj = self._mujoco
            if self._renderer is None:
                self._renderer = mj.Renderer(self._env.model, *self.image_size)
            r = self._renderer
            frames = []
            for v in self.views:
                r.update_scene(self._env.data, camera=v if v == "front" else self._camera(v))
                r.scene.flags[mj.mjtRndFlag.mjRND_SHADOW] = 0
                r.scene.flags[mj.mjtRndFlag.mjRND_REFLECTION] = 0
                if self.goal_marker:
                    self._draw_goal(r.scene)
                frames.append(r.render().copy())
            self._frames = np.stack(frames)
        return self._frames

    def _camera(self, view: str):
        mj = self._mujoco
        at, distance, azimuth, elevation = CAMERAS[view]
        c = mj.MjvCamera()
        c.type = mj.mjtCamera.mjCAMERA_FREE
        # the wrist camera's look-at point is an offset from the gripper: it follows the jaws
        origin = self._env.data.site("gripperframe").xpos if view == "wrist" else 0.0
        c.lookat[:] = np.asarray(at) + origin
        c.distance, c.azimuth, c.elevation = distance, azimuth, elevation
        return c

    def _draw_goal(self, scene) -> None:
        if scene.ngeom >= scene.maxgeom:
            return
        g = self.goal_pos()
        # a 1 mm disc on the floor (z = 0), under the block when it is placed
        self._mujoco.mjv_initGeom(scene.geoms[scene.ngeom], self._mujoco.mjtGeom.mjGEOM_CYLINDER,
                                  np.array([self._success_radius, 0.0, 0.0005]), np.array([g[0], g[1], 0.0005]),
                                  np.eye(3).reshape(-1), GOAL_RGBA)
        scene.ngeom += 1

    def close(self) -> None:
        """Free the GL context (at interpreter exit its collection prints EGL errors) and the simulator."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._gym.close()
