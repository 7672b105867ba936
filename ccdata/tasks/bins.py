"""BinPnP suite scene: carry the green cube from the source bin into the target bin.

Starts from Meta-World's bin-picking scene (`bin_start` at x = -0.12, `bin_goal` at x = +0.12,
both at y = 0.7). The layout never changes between the four tasks; only the bins' colours do,
so the suite composes along the perception axis. Meta-World's object is replaced by the
benchmark's cube so "the green cube" looks the same as in every other suite.

Success follows Meta-World's bin-picking (threshold 0.05): the cube's centre within 0.05 m of
the target bin's origin, the centre of its footprint at table height (z = 0). A cube resting
on the bin floor sits at z = 0.03, so it counts once it is within 4 cm (in x-y) of the
bin's centre.
"""

from __future__ import annotations

import numpy as np
from metaworld.utils import reward_utils

from ccdata.policies.base import Oracle, State, move, pose_action
from ccdata.tasks.base import SceneEnv, add_cube
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "bin-red-blue": ExplorationNoise(noise_std=0.5894, random_prob=0.1965),
    "bin-yellow-blue": ExplorationNoise(noise_std=0.5894, random_prob=0.1965),
    "bin-red-purple": ExplorationNoise(noise_std=0.5894, random_prob=0.1965),
    "bin-yellow-purple": ExplorationNoise(noise_std=0.5894, random_prob=0.1965),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

BIN_RGBA: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.1, 0.1, 1.0),
    "yellow": (0.95, 0.85, 0.1, 1.0),
    "blue": (0.1, 0.25, 0.9, 1.0),
    "purple": (0.55, 0.1, 0.75, 1.0),
}
"""Bin colours, chosen to stay distinct at 64 px (and from the green cube, magenta goals)."""

SOURCE_BIN, TARGET_BIN = "bin_start", "bin_goal"
SUCCESS_RADIUS = 0.05
"""Same as `add_free_box`'s default geom mass."""
CUBE_REST_Z = 0.03
"""Cube centre when resting on a bin floor (floor top at z = 0.01, half size 0.02)."""
CUBE_SPAWN_HALF_RANGE = np.array([0.06, 0.03])
"""Cube start offset (x, y) from the source bin's centre. The fingers close along y and open
to about +-5 cm, so y stays tighter to keep them clear of the bin walls (inner face 0.09)."""
WALL_CLEARANCE_Z = 0.1
"""Finger height the reward asks for away from the two bins' centres (walls end at 0.06)."""

# Oracle geometry, in the state's hand coordinates (the hand body sits 4.5 cm above the
# fingertips' centre).
GRASP_DZ = 0.04
"""Hand height above the cube's centre at which the fingers close."""
APPROACH_DZ = 0.12
"""Hover height above the cube before descending (fingertips above the walls)."""
CARRY_Z = 0.2
"""Hand height while carrying (the cube's bottom about 13 cm up, clear of the walls)."""
RELEASE_Z = 0.045
"""Cube-centre height at which the oracle opens the fingers over the target bin."""
XY_TOLERANCE = 0.008
Z_TOLERANCE = 0.01
CLOSE_STEPS = 8
DROP_DISTANCE = 0.04


class BinScene(SceneEnv):
    base_xml = "sawyer_xyz/sawyer_bin_picking.xml"

    def __init__(self, source_colour: str, target_colour: str) -> None:
        for colour in (source_colour, target_colour):
            if colour not in BIN_RGBA:
                raise ValueError(f"unknown bin colour {colour!r}; choose from {list(BIN_RGBA)}")
        self.colours = {SOURCE_BIN: source_colour, TARGET_BIN: target_colour}
        self.obj_init_pos = None
        super().__init__()

    def edit_spec(self, spec) -> None:
        spec.detach_body(spec.body("obj"))
        add_cube(spec, "cube", pos=(-0.12, 0.7, CUBE_REST_Z))
        for bin_name, colour in self.colours.items():
            self._paint(spec.body(bin_name), BIN_RGBA[colour])

    @staticmethod
    def _paint(body, rgba) -> None:
        # A geom's own rgba already wins over its material, but Meta-World's bin materials
        # are shiny and reflective; dropping them makes the four colours render alike.
        for geom in body.find_all("geom"):
            geom.material = ""
            geom.rgba = list(rgba)

    def _get_pos_objects(self) -> np.ndarray:
        return np.concatenate([self.data.body("cube").xpos.copy(), np.zeros(3)])

    def _get_quat_objects(self) -> np.ndarray:
        return np.concatenate([self.body_quat("cube"), [0.0, 0.0, 0.0, 1.0]])

    def reset_model(self) -> np.ndarray:
        self._reset_hand()
        centre = self.data.body(SOURCE_BIN).xpos[:2]
        offset = self.np_random.uniform(-CUBE_SPAWN_HALF_RANGE, CUBE_SPAWN_HALF_RANGE)
        self.obj_init_pos = np.array([*(centre + offset), CUBE_REST_Z])
        self.set_free_body("cubejoint", self.obj_init_pos)
        self._target_pos = self.data.body(TARGET_BIN).xpos.copy()
        self._target_to_obj_init = float(np.linalg.norm(self.obj_init_pos - self._target_pos))
        return self._get_obs()

    def evaluate_state(self, obs, action):
        cube = obs[4:7]
        to_target = float(np.linalg.norm(cube - self._target_pos))
        in_place = reward_utils.tolerance(
            to_target,
            bounds=(0.0, SUCCESS_RADIUS),
            margin=self._target_to_obj_init,
            sigmoid="long_tail",
        )
        caged = self._gripper_caging_reward(
            action,
            cube,
            obj_radius=0.015,
            pad_success_thresh=0.05,
            object_reach_radius=0.01,
            xz_thresh=0.01,
            desired_gripper_effort=0.7,
            high_density=True,
        )
        reward = reward_utils.hamacher_product(caged, in_place)
        near = bool(np.linalg.norm(cube - self.tcp_center) < 0.04)
        lifted = bool(cube[2] > self.obj_init_pos[2] + 0.02)
        # A gripper opening below ~0.43 means the fingers closed on nothing.
        holding = near and lifted and obs[3] >= 0.43
        if holding:
            reward += 1.0 + 5.0 * reward_utils.hamacher_product(self._wall_clearance(), in_place)
        success = to_target <= SUCCESS_RADIUS
        if success:
            reward = 10.0
        return reward, {
            "success": success,
            "obj_to_target": to_target,
            "grasp_reward": caged,
            "in_place_reward": in_place,
            "holding": holding,
        }

    def _wall_clearance(self) -> float:
        """1 while the fingers clear the bin walls, falling off as they dip below them.

        Directly over the cube's start or the target the hand may go low; elsewhere the
        required height ramps up to above the walls, so carrying the cube through a wall
        earns less than carrying it over.
        """
        tcp = self.tcp_center
        radius = min(
            np.linalg.norm(tcp[:2] - self.obj_init_pos[:2]),
            np.linalg.norm(tcp[:2] - self._target_pos[:2]),
        )
        floor = WALL_CLEARANCE_Z * np.clip((radius - 0.03) / 0.07, 0.0, 1.0)
        return reward_utils.tolerance(
            max(floor - tcp[2], 0.0), bounds=(0.0, 0.01), margin=0.05, sigmoid="long_tail"
        )


class BinOracle(Oracle):
    """Pick the cube straight up, carry it over the walls, lower it into the target bin."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._phase = "reach"
        self._closing_steps = 0

    def action(self, s: State) -> np.ndarray:
        hand, cube, goal = s.hand, s.obj1, s.goal
        grasp_point = cube + [0.0, 0.0, GRASP_DZ]
        if (
            self._phase in ("lift", "carry", "lower")
            and np.linalg.norm(hand - grasp_point) > DROP_DISTANCE
        ):
            # The cube slipped out: start over from wherever it lies.
            self.reset()
        if self._phase == "reach":
            # Hover above the cube, fingers open, high enough to clear the walls.
            above = np.array([cube[0], cube[1], max(hand[2], cube[2] + APPROACH_DZ)])
            if np.linalg.norm(hand[:2] - cube[:2]) < XY_TOLERANCE:
                self._phase = "descend"
            return pose_action(move(hand, above), -1.0)
        if self._phase == "descend":
            # Straight down until the open fingers straddle the cube.
            if abs(hand[2] - grasp_point[2]) < Z_TOLERANCE:
                self._phase = "close"
            return pose_action(move(hand, grasp_point), -1.0)
        if self._phase == "close":
            # Hold still while the fingers close.
            self._closing_steps += 1
            if self._closing_steps >= CLOSE_STEPS:
                self._phase = "lift"
            return pose_action(move(hand, grasp_point), 1.0)
        if self._phase == "lift":
            # Straight up to carrying height, above the bin walls.
            if hand[2] > CARRY_Z - Z_TOLERANCE:
                self._phase = "carry"
            return pose_action(move(hand, [hand[0], hand[1], CARRY_Z]), 1.0)
        # Steer the cube (not the hand) over the target; the grasp may sit off-centre.
        over_goal = hand + np.array([goal[0] - cube[0], goal[1] - cube[1], 0.0])
        if self._phase == "carry":
            over_goal[2] = CARRY_Z
            if np.linalg.norm(cube[:2] - goal[:2]) < XY_TOLERANCE:
                self._phase = "lower"
            return pose_action(move(hand, over_goal), 1.0)
        # Lower into the bin and let go just above its floor.
        over_goal[2] = hand[2] + (RELEASE_Z - cube[2])
        grip = -1.0 if cube[2] < RELEASE_Z + Z_TOLERANCE else 1.0
        return pose_action(move(hand, over_goal), grip)


_TASKS = (("red", "blue"), ("yellow", "blue"), ("red", "purple"), ("yellow", "purple"))
"""Curriculum order; the last pairs the second's source colour with the third's target."""

for _source, _target in _TASKS:
    register_task(
        TaskSpec(
            id=f"bin-{_source}-{_target}",
            title=f"cube from {_source} bin to {_target} bin",
            instruction=f"Move the green cube from the {_source} bin to the {_target} bin.",
            success=(
                f"cube centre within {SUCCESS_RADIUS} m of the {_target} bin's origin (centre "
                "of its footprint at table height), as in Meta-World's bin-picking"
            ),
            scene=lambda a=_source, b=_target: BinScene(a, b),
            oracle=BinOracle,
            exploration=EXPLORATION[f"bin-{_source}-{_target}"],
            components={
                "action": ("reach-object", "grasp", "lift", "transport", "release"),
                "perception": (f"{_source}-bin", f"{_target}-bin"),
            },
        )
    )
