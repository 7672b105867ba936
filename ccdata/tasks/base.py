"""The scene base class: a Meta-World Sawyer scene built from Meta-World's MJCF plus our edits.

A scene family subclasses `SceneEnv`, names the Meta-World file it starts from (`base_xml`),
adds what the benchmark needs in `edit_spec` (objects, colours, goal markers), places
objects in `reset_model` from `self.np_random`, and scores states in `evaluate_state`
(Meta-World convention: reward in [0, 10], `info["success"]`). The gymnasium-facing wrapper
(`ccdata.env.TaskEnv`) adds action repeat, termination, reward rescaling and cameras.
"""

from __future__ import annotations

import copy
from typing import Any, ClassVar

import mujoco
import numpy as np
from metaworld.asset_path_utils import full_V3_path_for
from metaworld.sawyer_xyz_env import SawyerXYZEnv
from scipy.spatial.transform import Rotation

_COMPILED: dict[tuple, mujoco.MjModel] = {}
"""Each scene's compiled model, by what built it (`SceneEnv._initialize_simulation`)."""

STATE_DIM = 39
"""Privileged state: hand (3), gripper (1), two objects pos+quat (14), previous 18, goal (3)."""

FRONTVIEW = {"pos": (0.0, 1.2, 1.0), "fovy": 60.0, "look_at": (0.0, 0.6, 0.0)}
"""The camera the authors added: in front of the table, looking back at it."""
TOPVIEW_FOVY = 50.0


def look_at_quat(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """MuJoCo camera quaternion (w, x, y, z) looking from `pos` at `target`, world z up."""
    forward = np.asarray(target, float) - np.asarray(pos, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    # MuJoCo cameras look along -z with +y up and +x right.
    rot = np.stack([right, up, -forward], axis=1)
    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    return np.array([w, x, y, z])


def add_benchmark_cameras(spec: mujoco.MjSpec) -> None:
    """Add `frontview` and widen/narrow `topview` as in the authors' setup."""
    pos = np.array(FRONTVIEW["pos"])
    spec.worldbody.add_camera(
        name="frontview",
        pos=pos,
        quat=look_at_quat(pos, np.array(FRONTVIEW["look_at"])),
        fovy=FRONTVIEW["fovy"],
    )
    spec.camera("topview").fovy = TOPVIEW_FOVY


GOAL_RGBA = (0.9, 0.1, 0.6, 1.0)
"""Goal markers are magenta in every scene (no object shares the colour)."""
CUBE_RGBA = (0.15, 0.7, 0.2, 1.0)
"""'The cube' is green wherever it appears (bins and blocks use red/yellow/blue/purple)."""
CUBE_HALF_SIZE = 0.02


def add_cube(spec: mujoco.MjSpec, name: str = "cube", pos=(0.0, 0.6, 0.02)) -> None:
    """The benchmark's cube: one size and colour in every scene it appears in."""
    add_free_box(spec, name, CUBE_HALF_SIZE, CUBE_RGBA, pos=pos)


def add_marker(spec: mujoco.MjSpec, name: str, rgba=GOAL_RGBA, size: float = 0.02) -> None:
    """A visual-only goal marker site (moved per episode through `model.site_pos`)."""
    spec.worldbody.add_site(
        name=name,
        pos=[0.0, 0.6, 0.2],
        size=[size, size, size],
        rgba=list(rgba),
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
    )


def add_free_box(
    spec: mujoco.MjSpec,
    name: str,
    half_size: float,
    rgba,
    pos=(0.0, 0.6, 0.02),
    mass: float = 0.1,
) -> None:
    """A free-floating cube `name` with geom `name + 'Geom'` (graspable by the Sawyer)."""
    body = spec.worldbody.add_body(name=name, pos=list(pos))
    # Meta-World's files compile inertia from geom groups 4-5 only (their collision geoms), so a
    # group-0 box would come out massless: give the body a solid cube's inertia explicitly.
    body.explicitinertial = True
    body.mass = mass
    body.ipos = [0.0, 0.0, 0.0]
    body.iquat = [1.0, 0.0, 0.0, 0.0]
    body.inertia = [mass * (2 * half_size) ** 2 / 6.0] * 3
    body.add_freejoint(name=name + "joint")
    body.add_geom(
        name=name + "Geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_size] * 3,
        rgba=list(rgba),
        mass=mass,
        friction=[1.0, 0.1, 0.002],
        condim=4,
        solref=[0.01, 1.0],
        solimp=[0.99, 0.99, 0.01, 0.5, 2.0],
    )


class SceneEnv(SawyerXYZEnv):
    """A Sawyer scene from `base_xml` (a Meta-World MJCF) with the benchmark's edits."""

    base_xml: ClassVar[str]
    """Meta-World MJCF under metaworld/assets, e.g. 'sawyer_xyz/sawyer_pick_place_v3.xml'."""
    hand_init: ClassVar[tuple[float, float, float]] = (0.0, 0.6, 0.2)
    hand_low: ClassVar[tuple[float, float, float]] = (-0.5, 0.40, 0.05)
    hand_high: ClassVar[tuple[float, float, float]] = (0.5, 1.0, 0.5)

    def __init__(self) -> None:
        super().__init__(hand_low=self.hand_low, hand_high=self.hand_high)
        self.hand_init_pos = np.array(self.hand_init, dtype=np.float64)
        # The benchmark drives the task itself: no Meta-World task objects, goal visible,
        # layouts drawn from our seeded generator (Meta-World's default is global np.random).
        self._set_task_called = True
        self._partially_observable = False
        self._freeze_rand_vec = False
        self.seeded_rand_vec = True
        self.max_path_length = 10**9

    @property
    def model_name(self) -> str:
        return full_V3_path_for(self.base_xml)

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        # Compiling the scene (its meshes) costs about 3x copying the compiled model, and a run
        # makes an environment per evaluation episode; an environment changes its own model
        # (goal sites), so each gets a copy of the pristine one. What `edit_spec` reads is set
        # on the instance by then, so the class and the instance's attributes key the cache.
        key = (type(self).__qualname__, repr(sorted(vars(self).items())))  # fullpath among them
        pristine = _COMPILED.get(key)
        if pristine is None:
            spec = mujoco.MjSpec.from_file(self.fullpath)
            add_benchmark_cameras(spec)
            self.edit_spec(spec)
            pristine = _COMPILED[key] = spec.compile()
        model = copy.copy(pristine)
        return model, mujoco.MjData(model)

    # --- what a family provides -------------------------------------------------------------

    def edit_spec(self, spec: mujoco.MjSpec) -> None:
        """Add or change what the Meta-World file lacks (objects, colours, markers)."""

    def reset_model(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # --- shared machinery -------------------------------------------------------------------

    def body_quat(self, name: str) -> np.ndarray:
        return Rotation.from_matrix(self.data.body(name).xmat.reshape(3, 3)).as_quat()

    def set_free_body(self, joint: str, pos, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Teleport a free joint to `pos` at rest."""
        jnt = self.model.joint(joint)
        qadr, vadr = jnt.qposadr[0], jnt.dofadr[0]
        qpos, qvel = self.data.qpos.copy(), self.data.qvel.copy()
        qpos[qadr : qadr + 3] = pos
        qpos[qadr + 3 : qadr + 7] = quat
        qvel[vadr : vadr + 6] = 0.0
        self.set_state(qpos, qvel)

    def set_site(self, name: str, pos) -> None:
        self.model.site(name).pos = np.asarray(pos, dtype=np.float64)

    def reset_scene(self, rng: np.random.Generator) -> np.ndarray:
        """Reset physics and draw a layout from `rng`; returns the 39-D state."""
        self.np_random = rng
        mujoco.mj_resetData(self.model, self.data)
        self.curr_path_length = 0
        self.reset_model()
        mujoco.mj_forward(self.model, self.data)
        self._prev_obs = self._get_curr_obs_combined_no_goal()
        return self._get_obs()

    def sim_step(self, action: np.ndarray) -> tuple[np.ndarray, float, dict[str, Any]]:
        """One Meta-World step (frame_skip physics steps): (state, reward in [0, 10], info)."""
        self.set_xyz_action(action[:3])
        self.do_simulation([action[-1], -action[-1]], n_frames=self.frame_skip)
        self.curr_path_length += 1
        for site in self._target_site_config:
            self._set_pos_site(*site)
        mujoco.mj_forward(self.model, self.data)
        state = self._get_obs()
        reward, info = self.evaluate_state(state, action)
        return state, float(reward), info

    @property
    def _target_site_config(self) -> list:
        # Markers live in model.site_pos and are placed by reset_model; nothing to re-pin.
        return []
