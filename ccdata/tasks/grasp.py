"""Grasp suite scene: the Sawyer, the table, the benchmark cube and a magenta goal marker.

One scene serves the suite's three tasks; they differ only in the episode layout and what
counts as success:

- pick-cube: the cube lies on the table, the marker floats just above it; lift it there.
- place-cube: the episode starts with the cube held above the table; put it at the marker on
  the table.
- pnp-cube: Meta-World pick-place: cube on the table, marker anywhere over the table.

This module also holds what the block scenes (`ccdata.tasks.blocks`) reuse: the shaped
transport reward and the scripted grasp-carry-release oracle.
"""

from __future__ import annotations

import numpy as np
from metaworld.utils import reward_utils

from ccdata.policies.base import Oracle, State, move, pose_action
from ccdata.tasks.base import CUBE_HALF_SIZE, SceneEnv, add_cube, add_marker
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "pick-cube": ExplorationNoise(noise_std=0.699, random_prob=0.233),
    "place-cube": ExplorationNoise(noise_std=1.3193, random_prob=0.4398),
    "pnp-cube": ExplorationNoise(noise_std=0.6683, random_prob=0.2228),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

REST_Z = CUBE_HALF_SIZE
"""Height of a cube's centre when it rests on the table."""
START_LOW = np.array([-0.12, 0.55])
START_HIGH = np.array([0.12, 0.75])
"""Where objects (and the hand of place-cube) start, well inside the reachable area."""
TABLE_LOW = np.array([-0.15, 0.5])
TABLE_HIGH = np.array([0.15, 0.8])
"""Where goals on or over the table may be."""
MIN_SEPARATION = 0.12
"""Minimum xy distance between a start and its goal, so that every task needs transport."""
PICK_RADIUS = 0.05
PLACE_RADIUS = 0.07
"""Success radii: Meta-World's pick-place threshold for placing; pick is stricter because
its marker is only 0.1-0.2 m above the cube."""
GRASP_INIT_STEPS = 15
"""Meta-World steps of closing the gripper while the place-cube layout is built."""


def pads_touch(scene: SceneEnv, geom_id: int) -> bool:
    """Whether either finger pad is in contact with geom `geom_id`."""
    pads = {scene.data.geom("leftpad_geom").id, scene.data.geom("rightpad_geom").id}
    for contact in scene.data.contact[: scene.data.ncon]:
        pair = {contact.geom1, contact.geom2}
        if geom_id in pair and pair & pads:
            return True
    return False


def is_held(scene: SceneEnv, geom_name: str, pos: np.ndarray) -> bool:
    """Both pads press on the object and it is off the table."""
    return bool(scene.touching_object(scene.data.geom(geom_name).id) and pos[2] > REST_Z + 0.01)


def transport_reward(
    scene: SceneEnv,
    action: np.ndarray,
    geom_name: str,
    pos: np.ndarray,
    start: np.ndarray,
    target: np.ndarray,
    radius: float,
) -> float:
    """Meta-World pick-place style shaping in [0, 10] for moving one object to `target`.

    Caging-and-gripping times closeness to the target while the object is free; once it is
    held off the table, a bonus of 1 + 5 * closeness. 10 is left to the caller (success).
    """
    # The base caging reward measures progress from `obj_init_pos`.
    scene.obj_init_pos = np.asarray(start, dtype=np.float64)
    distance = float(np.linalg.norm(pos - target))
    margin = max(float(np.linalg.norm(start - target)), radius + 1e-3)
    in_place = reward_utils.tolerance(
        distance, bounds=(0, radius), margin=margin, sigmoid="long_tail"
    )
    caging = scene._gripper_caging_reward(
        action,
        pos,
        obj_radius=CUBE_HALF_SIZE,
        pad_success_thresh=0.05,
        object_reach_radius=0.01,
        xz_thresh=0.01,
        high_density=True,
    )
    reward = reward_utils.hamacher_product(caging, in_place)
    if is_held(scene, geom_name, pos):
        reward += 1.0 + 5.0 * in_place
    return float(np.clip(reward, 0.0, 10.0))


def sample_xy(rng: np.random.Generator, low, high, away_from=(), min_distance=MIN_SEPARATION):
    """A uniform xy point in [low, high] at least `min_distance` from every point given."""
    while True:
        xy = rng.uniform(low, high)
        if all(np.linalg.norm(xy - np.asarray(p)[:2]) >= min_distance for p in away_from):
            return xy


class GraspScene(SceneEnv):
    base_xml = "sawyer_xyz/sawyer_pick_place_v3.xml"

    MODES = ("pick", "place", "pnp")

    def __init__(self, mode: str) -> None:
        if mode not in self.MODES:
            raise ValueError(f"unknown grasp mode {mode!r}; choose one of {self.MODES}")
        self.mode = mode
        self.radius = PICK_RADIUS if mode == "pick" else PLACE_RADIUS
        super().__init__()

    def edit_spec(self, spec) -> None:
        # Meta-World's pick-place puck and goal give way to the benchmark's cube and marker.
        spec.detach_body(spec.body("obj"))
        spec.site("goal").delete()
        add_cube(spec)
        add_marker(spec, "goal")

    def _get_id_main_object(self) -> int:
        return self.data.geom("cubeGeom").id

    def _get_pos_objects(self) -> np.ndarray:
        return self.data.body("cube").xpos.copy()

    def _get_quat_objects(self) -> np.ndarray:
        return self.body_quat("cube")

    # --- layouts ------------------------------------------------------------------------------

    def reset_model(self) -> np.ndarray:
        rng = self.np_random
        if self.mode == "place":
            start, goal = self._layout_held(rng)
        else:
            cube_xy = rng.uniform(START_LOW, START_HIGH)
            self.hand_init_pos = np.array(self.hand_init)
            self._reset_hand()
            start = np.array([*cube_xy, REST_Z])
            self.set_free_body("cubejoint", start)
            if self.mode == "pick":
                # The marker floats over the cube: lifting is the whole task.
                goal = start + np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(0.1, 0.2)])
            else:
                goal_xy = sample_xy(rng, TABLE_LOW, TABLE_HIGH, away_from=[start])
                goal = np.array([*goal_xy, rng.uniform(0.05, 0.25)])
        self.obj_init_pos = self._get_pos_objects()
        self._start = self.obj_init_pos.copy()
        self._target_pos = goal
        self.set_site("goal", goal)
        return self._get_obs()

    def _layout_held(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Hand above a random point with the cube closed between its fingers."""
        hand_xy = rng.uniform(START_LOW, START_HIGH)
        self.hand_init_pos = np.array([*hand_xy, rng.uniform(0.17, 0.25)])
        self._reset_hand()
        self.set_free_body("cubejoint", self.tcp_center.copy())
        # Close without gravity so the cube cannot fall before the pads reach it.
        gravity = self.model.opt.gravity.copy()
        self.model.opt.gravity[:] = 0.0
        try:
            for _ in range(GRASP_INIT_STEPS):
                self.do_simulation([1.0, -1.0], self.frame_skip)
        finally:
            self.model.opt.gravity[:] = gravity
        for _ in range(GRASP_INIT_STEPS):
            self.do_simulation([1.0, -1.0], self.frame_skip)
        cube = self._get_pos_objects()
        if not is_held(self, "cubeGeom", cube):
            raise RuntimeError(f"place-cube layout: the cube slipped out of the gripper at {cube}")
        # The caging reward scales by the hand's start distance to the object, which is zero
        # here; measure a re-grasp from 10 cm above instead.
        self.init_tcp = cube + np.array([0.0, 0.0, 0.1])
        goal_xy = sample_xy(rng, TABLE_LOW, TABLE_HIGH, away_from=[cube])
        return cube, np.array([*goal_xy, REST_Z])

    # --- scoring ------------------------------------------------------------------------------

    def evaluate_state(self, obs, action):
        cube = obs[4:7]
        distance = float(np.linalg.norm(cube - self._target_pos))
        success = distance <= self.radius
        if success:
            reward = 10.0
        else:
            reward = transport_reward(
                self, action, "cubeGeom", cube, self._start, self._target_pos, self.radius
            )
        return reward, {"success": bool(success), "distance": distance}


# --- oracle -------------------------------------------------------------------------------------

TCP_BELOW_HAND = 0.045
"""The fingertip centre sits this far below the hand position reported in the state."""
OPEN, CLOSE = -1.0, 1.0


class PickPlaceOracle(Oracle):
    """Approach, descend, close, lift, carry to the goal, and (for table goals) lower, open,
    retreat. Reused by the block tasks with a different object slot and target."""

    carry_height = 0.15
    """Height of the fingertip centre while carrying between distant points."""
    grasp_offset = 0.0
    """Fingertip centre height above the object's centre when closing."""
    release = True
    """Open at the goal (table goals) or just hold the object at it (air goals)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.phase = "approach"
        self.timer = 0

    def object_and_target(self, s: State) -> tuple[np.ndarray, np.ndarray]:
        return s.obj1, s.goal

    def action(self, s: State) -> np.ndarray:
        obj, target = self.object_and_target(s)
        return self.step(s, obj, target)

    def step(self, s: State, obj: np.ndarray, target: np.ndarray) -> np.ndarray:
        tcp = s.hand - np.array([0.0, 0.0, TCP_BELOW_HAND])
        grasp_point = obj + np.array([0.0, 0.0, self.grasp_offset])
        held_far = self.phase in ("lift", "carry", "lower") and np.linalg.norm(tcp - obj) > 0.04
        if held_far:
            # The object slipped: start over from above it.
            self.phase = "approach"
        if self.phase == "approach":
            # Fly above the object with the gripper open.
            above = np.array([*grasp_point[:2], max(grasp_point[2] + 0.08, tcp[2])])
            if np.linalg.norm(tcp[:2] - obj[:2]) < 0.01:
                self.phase = "descend"
            return pose_action(move(tcp, above, 15.0), OPEN)
        if self.phase == "descend":
            # Lower straight onto the object.
            if np.linalg.norm(tcp - grasp_point) < 0.008:
                self.phase, self.timer = "close", 0
            return pose_action(move(tcp, grasp_point, 15.0), OPEN)
        if self.phase == "close":
            # Squeeze in place until the fingers have settled on the object.
            self.timer += 1
            if self.timer >= 6:
                self.phase = "lift"
            return pose_action(move(tcp, grasp_point, 15.0), CLOSE)
        if self.phase == "lift":
            # Raise the object clear of the table before moving sideways.
            lift_z = max(self.carry_height if self.release else 0.07, target[2])
            if tcp[2] > lift_z - 0.02 or np.linalg.norm(tcp[:2] - target[:2]) < 0.02:
                self.phase = "carry"
            return pose_action(move(tcp, [*tcp[:2], lift_z], 15.0), CLOSE)
        # From here on, aim the object rather than the hand: the grasp may be off-centre.
        dest = tcp + (target - obj)
        if self.phase == "carry":
            # Carry to the goal (above it, for goals on the table).
            if self.release:
                dest[2] = max(self.carry_height, target[2])
                if np.linalg.norm(obj[:2] - target[:2]) < 0.008:
                    self.phase = "lower"
            return pose_action(move(tcp, dest, 15.0), CLOSE)
        if self.phase == "lower":
            # Set the object down at the goal.
            if np.linalg.norm(obj - target) < 0.008:
                self.phase, self.timer = "open", 0
            return pose_action(move(tcp, dest, 15.0), CLOSE)
        if self.phase == "open":
            # Let go without moving.
            self.timer += 1
            if self.timer >= 4:
                self.phase = "retreat"
            return pose_action(np.zeros(3), OPEN)
        # Retreat: back up, gripper open.
        return pose_action(move(tcp, [*tcp[:2], obj[2] + 0.12], 15.0), OPEN)


class PickOracle(PickPlaceOracle):
    release = False


class PlaceOracle(PickPlaceOracle):
    """The cube starts in the hand: skip straight to carrying it."""

    def reset(self) -> None:
        super().reset()
        self.phase = "carry"


PNP_CUBE_SUCCESS = f"cube centre within {PLACE_RADIUS} m of the marker"
PNP_CUBE_INSTRUCTION = "Pick up the green cube and place it at the magenta marker."

register_task(
    TaskSpec(
        id="pick-cube",
        title="pick cube",
        instruction="Pick up the green cube from the table and lift it to the magenta marker.",
        success=f"cube centre within {PICK_RADIUS} m of the marker floating above its start",
        scene=lambda: GraspScene("pick"),
        oracle=PickOracle,
        exploration=EXPLORATION["pick-cube"],
        components={"action": ("reach-object", "grasp", "lift"), "perception": ("cube",)},
    )
)
register_task(
    TaskSpec(
        id="place-cube",
        title="place cube",
        instruction="Carry the green cube you are holding to the magenta marker and release it.",
        success=f"cube centre within {PLACE_RADIUS} m of the marker on the table",
        scene=lambda: GraspScene("place"),
        oracle=PlaceOracle,
        exploration=EXPLORATION["place-cube"],
        components={"action": ("transport", "release"), "perception": ("cube",)},
    )
)
register_task(
    TaskSpec(
        id="pnp-cube",
        title="pick and place cube",
        instruction=PNP_CUBE_INSTRUCTION,
        success=PNP_CUBE_SUCCESS,
        scene=lambda: GraspScene("pnp"),
        oracle=PickOracle,
        exploration=EXPLORATION["pnp-cube"],
        components={
            "action": ("reach-object", "grasp", "lift", "transport", "release"),
            "perception": ("cube",),
        },
    )
)
