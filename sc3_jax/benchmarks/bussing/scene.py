"""The MuJoCo scene (MJCF written here) and a headless multi-view renderer.

Scene: a table (surface at z = 0), a mocap-driven parallel gripper (two slide fingers on position actuators, a wrist
camera on the palm), the six objects of ``tasks.OBJECTS`` (those not used by an episode are parked far off-table),
an open utensil bin and a taller trash can (mocap bodies, so that each episode can move them), and two tightly framed
third-person cameras ("left", "right"). The gripper and fingers do not collide with anything (see ``env.py`` for the
grasp model); objects collide with the table, the containers and each other.

Rendering: ``MUJOCO_GL`` defaults to ``egl`` (on this Debian image the OSMesa library is absent and ``osmesa`` fails
at import); shadows and reflections are off (a 4096^2 shadow map made every frame ~20 ms on llvmpipe; without it a
64x64 view renders in well under 1 ms).
"""
from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from .tasks import OBJECTS  # noqa: E402

VIEWS = ("left", "right", "wrist")
DEFAULT_IMAGE_SIZE = (64, 64)

# Container geometry (inner half width, wall height, wall thickness, floor thickness).
BIN_INNER, BIN_WALL_H = 0.080, 0.055
CAN_INNER, CAN_WALL_H = 0.068, 0.085
WALL_T, FLOOR_T = 0.008, 0.008
CONTAINER_GEOM = {"bin": (BIN_INNER, BIN_WALL_H), "can": (CAN_INNER, CAN_WALL_H)}

OPEN_WIDTH = 0.09  # finger gap when open (m)
PARK_XY = np.array([3.0, 3.0])  # objects not in the episode are parked here (off camera)


def _container_xml(name: str, inner: float, height: float, rgba: str) -> str:
    h, t = height / 2, WALL_T / 2
    o = inner + t
    geoms = [f'<geom name="{name}_floor" type="box" size="{inner + WALL_T} {inner + WALL_T} {FLOOR_T / 2}" '
             f'pos="0 0 {FLOOR_T / 2}" rgba="{rgba}"/>']
    for i, (x, y, sx, sy) in enumerate([(o, 0, t, inner + WALL_T), (-o, 0, t, inner + WALL_T),
                                        (0, o, inner, t), (0, -o, inner, t)]):
        geoms.append(f'<geom name="{name}_wall{i}" type="box" size="{sx} {sy} {h}" pos="{x} {y} {h}" rgba="{rgba}"/>')
    return (f'<body name="{name}" mocap="true" pos="0 0 0">' + "".join(geoms) + "</body>")


def _object_xml(i: int) -> str:
    o = OBJECTS[i]
    size = " ".join(f"{s:g}" for s in o.size)
    rgba = " ".join(f"{c:g}" for c in o.rgba)
    return (f'<body name="obj_{o.name}" pos="{PARK_XY[0] + 0.2 * i} {PARK_XY[1]} {o.half_height}">'
            f'<freejoint name="obj_{o.name}_joint"/>'
            f'<geom name="obj_{o.name}_geom" type="{o.geom}" size="{size}" rgba="{rgba}" mass="0.06" '
            f'friction="1.0 0.01 0.001" condim="4"/></body>')


def scene_xml(image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE) -> str:
    h, w = image_size
    off_w, off_h = max(640, w), max(480, h)
    objects = "".join(_object_xml(i) for i in range(len(OBJECTS)))
    grip_rgba = "0.18 0.18 0.2 1"
    return f"""
<mujoco model="sc3_table_bussing">
  <option timestep="0.002" gravity="0 0 -9.81" integrator="implicitfast"/>
  <visual>
    <global offwidth="{off_w}" offheight="{off_h}"/>
    <quality shadowsize="0" offsamples="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0.05 0.05 0.05"/>
  </visual>
  <default>
    <geom solref="0.004 1" solimp="0.95 0.99 0.001"/>
  </default>
  <worldbody>
    <light name="top" pos="0 0 1.5" dir="0 0 -1" diffuse="0.35 0.35 0.35" castshadow="false"/>
    <geom name="floor" type="plane" size="6 6 0.1" pos="0 0 -0.75" rgba="0.35 0.35 0.38 1"/>
    <geom name="table" type="box" size="0.40 0.33 0.375" pos="0.02 0 -0.375" rgba="0.78 0.70 0.58 1"
          friction="1.0 0.01 0.001"/>
    <body name="ws_center" pos="0.05 0 0.0"/>
    <camera name="left" pos="-0.30 0.34 0.60" mode="targetbody" target="ws_center" fovy="45"/>
    <camera name="right" pos="-0.30 -0.34 0.60" mode="targetbody" target="ws_center" fovy="45"/>
    <body name="gripper" mocap="true" pos="-0.05 0 0.18">
      <geom name="palm" type="box" size="0.018 0.058 0.014" pos="0 0 0.078" rgba="{grip_rgba}"
            contype="0" conaffinity="0"/>
      <geom name="wrist_link" type="cylinder" size="0.016 0.09" pos="0 0 0.18" rgba="0.55 0.55 0.6 1"
            contype="0" conaffinity="0"/>
      <camera name="wrist" pos="-0.055 0 0.075" xyaxes="0 -1 0 0.866 0 0.5" fovy="75"/>
      <body name="finger_l" pos="0 0 0">
        <joint name="finger_l_joint" type="slide" axis="0 1 0" range="0 {OPEN_WIDTH / 2}" damping="2"/>
        <geom name="finger_l_geom" type="box" size="0.012 0.006 0.036" pos="0 0.006 0.032" rgba="0.9 0.9 0.92 1"
              contype="0" conaffinity="0" mass="0.02"/>
      </body>
      <body name="finger_r" pos="0 0 0">
        <joint name="finger_r_joint" type="slide" axis="0 -1 0" range="0 {OPEN_WIDTH / 2}" damping="2"/>
        <geom name="finger_r_geom" type="box" size="0.012 0.006 0.036" pos="0 -0.006 0.032" rgba="0.9 0.9 0.92 1"
              contype="0" conaffinity="0" mass="0.02"/>
      </body>
    </body>
    {_container_xml("bin", BIN_INNER, BIN_WALL_H, "0.55 0.80 0.95 1")}
    {_container_xml("can", CAN_INNER, CAN_WALL_H, "0.22 0.22 0.24 1")}
    {objects}
  </worldbody>
  <actuator>
    <position name="finger_l_act" joint="finger_l_joint" kp="300" ctrlrange="0 {OPEN_WIDTH / 2}"/>
    <position name="finger_r_act" joint="finger_r_joint" kp="300" ctrlrange="0 {OPEN_WIDTH / 2}"/>
  </actuator>
</mujoco>
"""


def build_model(image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(scene_xml(image_size))


class MultiViewRenderer:
    """Renders the named cameras to uint8 [H, W, 3] arrays (one GL context, shadows/reflections off)."""

    def __init__(self, model: mujoco.MjModel, image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
                 views: tuple[str, ...] = VIEWS):
        self.model, self.views = model, tuple(views)
        self.height, self.width = int(image_size[0]), int(image_size[1])
        self._renderer = mujoco.Renderer(model, self.height, self.width)
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._cam_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, v) for v in self.views]
        if min(self._cam_ids) < 0:
            raise ValueError(f"unknown camera among {self.views}")

    def render(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        out = {}
        for view, cid in zip(self.views, self._cam_ids):
            self._renderer.update_scene(data, camera=cid)
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            out[view] = self._renderer.render().copy()
        return out

    def close(self) -> None:
        self._renderer.close()
