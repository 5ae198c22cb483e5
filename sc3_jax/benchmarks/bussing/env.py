"""The bussing environment: reset / step / observe with a 7-D delta end-effector action interface.

Action (float [7], raw units, the same for the expert, the policies and the episode store):
    (dx, dy, dz) metres, (rx, ry, rz) axis-angle radians (applied in the world frame, left-multiplied),
    gripper target width in metres (0 = closed, ``OPEN_WIDTH`` = open).
Translation steps are clipped to ``MAX_STEP`` per control step and rotation steps to ``MAX_ROT``; the commanded pose
is clipped to the workspace box. Control at ``control_hz`` (20 Hz default; 10 Hz available), physics at 500 Hz; the
mocap target is interpolated linearly over the physics sub-steps.

End-effector pose (float [7]): the grip point between the fingertips (x, y, z), the gripper orientation as a
rotation vector, and the measured finger gap. It is recorded every control step (pseudo-actions can be derived
from consecutive poses).

Grasp model ("grasp attach", documented in docs/sim.md): the fingers are visual and do not collide. When the gripper
is commanded closed (target width < ``GRASP_CMD``) and an object's centre is within ``GRASP_TOL`` of the grip point
horizontally and the grip point is between the object's bottom and top (with a small margin), the object is attached
rigidly to the gripper (its free joint follows the gripper every physics sub-step) and the fingers close on its
width. Commanding the gripper open (target > ``RELEASE_CMD``) detaches it and it falls under physics. This makes the
expert reliable while keeping lifting (grasp position), transport and placing (release position, falling, bouncing
off walls) physical and observable.
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from . import scene as S
from .tasks import OBJECT_BY_NAME, OBJECTS, InitialCondition, make_initial_condition, task_id

MAX_STEP = 0.04  # m per control step
MAX_ROT = 0.3  # rad per control step
WORKSPACE_LO = np.array([-0.36, -0.32, 0.005])
WORKSPACE_HI = np.array([0.40, 0.32, 0.35])
HOME_POS = np.array([-0.05, 0.0, 0.18])
GRASP_CMD = 0.02
RELEASE_CMD = 0.045
GRASP_TOL = 0.03
CONTROL_HZ = 20  # the simulator's control (and frame) rate unless a caller picks 10 (`sc3 sim demos/mixture`)
PHYSICS_DT = 0.002


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    if q[0] < 0:
        q = -q
    s = np.linalg.norm(q[1:])
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(s, q[0])
    return q[1:] / s * angle


def rotvec_to_quat(r: np.ndarray) -> np.ndarray:
    r = np.asarray(r, np.float64)
    a = np.linalg.norm(r)
    if a < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * r / a])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, np.float64), np.asarray(b, np.float64))
    return out


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


@dataclasses.dataclass
class StepInfo:
    grasped: str | None = None  # object attached this step
    released: str | None = None  # object released this step


class BussingEnv:
    """One simulated table. ``reset(seed, task)`` then ``step(action)``; ``observe()`` renders the views."""

    def __init__(self, image_size: tuple[int, int] = S.DEFAULT_IMAGE_SIZE, views: tuple[str, ...] = S.VIEWS,
                 control_hz: int = 20, n_objects: int = 3, render: bool = True):
        if control_hz not in (10, 20):
            raise ValueError("control_hz must be 20 or 10")
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.views = tuple(views)
        self.control_hz, self.n_objects = control_hz, n_objects
        self.model = S.build_model(self.image_size)
        self.data = mujoco.MjData(self.model)
        self.substeps = int(round(1.0 / control_hz / PHYSICS_DT))
        self.renderer = S.MultiViewRenderer(self.model, self.image_size, self.views) if render else None
        m = self.model
        self._gripper_mocap = m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "gripper")]
        self._container_mocap = {c: m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, c)]
                                 for c in ("bin", "can")}
        self._qadr = {}
        self._vadr = {}
        for o in OBJECTS:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"obj_{o.name}_joint")
            self._qadr[o.name], self._vadr[o.name] = m.jnt_qposadr[j], m.jnt_dofadr[j]
        self._finger_q = [m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"finger_{s}_joint")]
                          for s in "lr"]
        self.ic: InitialCondition | None = None
        self.t = 0

    # -- episode -------------------------------------------------------------------------------------------------
    def reset(self, seed: int | InitialCondition = 0, task: str | int = "bussing") -> dict:
        ic = seed if isinstance(seed, InitialCondition) else make_initial_condition(seed, task, self.n_objects)
        self.ic = ic
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        for i, o in enumerate(OBJECTS):
            a = self._qadr[o.name]
            if o.name in ic.objects:
                k = ic.objects.index(o.name)
                d.qpos[a:a + 3] = [ic.object_xy[k, 0], ic.object_xy[k, 1], o.half_height + 0.001]
                d.qpos[a + 3:a + 7] = _yaw_quat(ic.object_yaw[k])
            else:
                d.qpos[a:a + 3] = [S.PARK_XY[0] + 0.2 * i, S.PARK_XY[1], o.half_height + 0.001 - 0.75]
                d.qpos[a + 3:a + 7] = [1, 0, 0, 0]
        d.mocap_pos[self._container_mocap["bin"]] = [ic.bin_xy[0], ic.bin_xy[1], 0.0]
        d.mocap_pos[self._container_mocap["can"]] = [ic.can_xy[0], ic.can_xy[1], 0.0]
        self.target_pos = HOME_POS.copy()
        self.target_quat = np.array([1.0, 0, 0, 0])
        self.gripper_cmd = S.OPEN_WIDTH
        d.mocap_pos[self._gripper_mocap] = self.target_pos
        d.mocap_quat[self._gripper_mocap] = self.target_quat
        for q in self._finger_q:
            d.qpos[q] = S.OPEN_WIDTH / 2
        d.ctrl[:] = S.OPEN_WIDTH / 2
        self.held: str | None = None
        self._held_rel = None
        self.t = 0
        mujoco.mj_forward(m, d)
        # let objects settle on the table (not part of the episode)
        for _ in range(50):
            mujoco.mj_step(m, d)
        self.task_id = task_id(ic.task)
        return self.observe() if self.renderer is not None else {}

    # -- state ---------------------------------------------------------------------------------------------------
    def object_pos(self, name: str) -> np.ndarray:
        a = self._qadr[name]
        return self.data.qpos[a:a + 3].copy()

    def object_quat(self, name: str) -> np.ndarray:
        a = self._qadr[name]
        return self.data.qpos[a + 3:a + 7].copy()

    def object_speed(self, name: str) -> float:
        v = self._vadr[name]
        return float(np.linalg.norm(self.data.qvel[v:v + 3]))

    def object_positions(self) -> np.ndarray:
        """[n, 3] positions of the episode's objects in ``ic.objects`` order."""
        return np.stack([self.object_pos(n) for n in self.ic.objects])

    def container_xy(self, name: str) -> np.ndarray:
        return self.data.mocap_pos[self._container_mocap[name], :2].copy()

    def gripper_width(self) -> float:
        return float(sum(self.data.qpos[q] for q in self._finger_q))

    def ee_pose(self) -> np.ndarray:
        d = self.data
        pos = d.mocap_pos[self._gripper_mocap]
        rv = quat_to_rotvec(d.mocap_quat[self._gripper_mocap])
        return np.concatenate([pos, rv, [self.gripper_width()]]).astype(np.float32)

    def render(self) -> dict[str, np.ndarray]:
        if self.renderer is None:
            raise RuntimeError("environment created with render=False")
        return self.renderer.render(self.data)

    def observe(self) -> dict:
        frames = self.render()
        return {"images": np.stack([frames[v] for v in self.views]), "state": self.ee_pose(),
                "task": np.int32(self.task_id), "frames": frames}

    # -- stepping ------------------------------------------------------------------------------------------------
    def _grip_width_for(self, name: str) -> float:
        o = OBJECT_BY_NAME[name]
        if o.geom in ("cylinder",):
            w = 2 * o.size[0]
        elif o.geom == "box":
            w = 2 * o.size[1]
        else:
            w = 2 * min(o.size[0], o.size[1])
        return float(min(w, S.OPEN_WIDTH))

    def _try_grasp(self) -> str | None:
        ee = self.data.mocap_pos[self._gripper_mocap]
        best, best_d = None, np.inf
        for name in self.ic.objects:
            p = self.object_pos(name)
            hh = OBJECT_BY_NAME[name].half_height
            dxy = np.linalg.norm(p[:2] - ee[:2])
            if dxy < GRASP_TOL and p[2] - hh - 0.012 <= ee[2] <= p[2] + hh + 0.012 and dxy < best_d:
                best, best_d = name, dxy
        return best

    def _set_held_pose(self) -> None:
        d = self.data
        gpos, gquat = d.mocap_pos[self._gripper_mocap], d.mocap_quat[self._gripper_mocap]
        rel_pos, rel_quat = self._held_rel
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, gquat)
        a, v = self._qadr[self.held], self._vadr[self.held]
        d.qpos[a:a + 3] = gpos + rot.reshape(3, 3) @ rel_pos
        d.qpos[a + 3:a + 7] = quat_mul(gquat, rel_quat)
        d.qvel[v:v + 6] = 0.0

    def step(self, action: np.ndarray, render: bool = False) -> StepInfo:
        """Apply one 7-D delta-EE action for one control period. Returns what happened (grasp/release)."""
        a = np.asarray(action, np.float64).reshape(7)
        if not np.all(np.isfinite(a)):
            a = np.nan_to_num(a)
        info = StepInfo()
        d = self.data
        dpos = a[:3]
        n = np.linalg.norm(dpos)
        if n > MAX_STEP:
            dpos = dpos * (MAX_STEP / n)
        drot = a[3:6]
        r = np.linalg.norm(drot)
        if r > MAX_ROT:
            drot = drot * (MAX_ROT / r)
        prev_pos = d.mocap_pos[self._gripper_mocap].copy()
        self.target_pos = np.clip(self.target_pos + dpos, WORKSPACE_LO, WORKSPACE_HI)
        self.target_quat = quat_mul(rotvec_to_quat(drot), self.target_quat)
        self.target_quat /= np.linalg.norm(self.target_quat)
        self.gripper_cmd = float(np.clip(a[6], 0.0, S.OPEN_WIDTH))
        if self.held is not None and self.gripper_cmd > RELEASE_CMD:
            info.released = self.held
            self.held, self._held_rel = None, None
        finger = self.gripper_cmd if self.held is None else max(self.gripper_cmd, self._grip_width_for(self.held))
        d.ctrl[:] = finger / 2
        d.mocap_quat[self._gripper_mocap] = self.target_quat
        for k in range(1, self.substeps + 1):
            d.mocap_pos[self._gripper_mocap] = prev_pos + (self.target_pos - prev_pos) * (k / self.substeps)
            if self.held is not None:
                self._set_held_pose()
            mujoco.mj_step(self.model, d)
        if self.held is None and self.gripper_cmd < GRASP_CMD and info.released is None:
            name = self._try_grasp()
            if name is not None:
                gpos, gquat = d.mocap_pos[self._gripper_mocap].copy(), d.mocap_quat[self._gripper_mocap].copy()
                rot = np.zeros(9)
                mujoco.mju_quat2Mat(rot, gquat)
                rel_pos = rot.reshape(3, 3).T @ (self.object_pos(name) - gpos)
                ginv = gquat * np.array([1, -1, -1, -1])
                self.held, self._held_rel = name, (rel_pos, quat_mul(ginv, self.object_quat(name)))
                d.ctrl[:] = max(self.gripper_cmd, self._grip_width_for(name)) / 2
                for q in self._finger_q:  # fingers snap onto the object so the held state is visible at once
                    d.qpos[q] = max(self.gripper_cmd, self._grip_width_for(name)) / 2
                mujoco.mj_forward(self.model, d)
                info.grasped = name
        self.t += 1
        return info

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
