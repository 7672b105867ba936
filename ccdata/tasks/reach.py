"""Reach suite scene: the Sawyer, the table and a visible goal marker.

The goal varies only in the task's plane; the remaining coordinate equals the hand's start,
so reach-xy, reach-xz and reach-yz exercise two displacement axes each and reach-xyz all three.
"""

from __future__ import annotations

import numpy as np
from metaworld.utils import reward_utils

from ccdata.policies.base import Oracle, State, move, pose_action
from ccdata.tasks.base import SceneEnv, add_marker
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "reach-xy": ExplorationNoise(noise_std=2.2979, random_prob=0.766),
    "reach-xz": ExplorationNoise(noise_std=2.3784, random_prob=0.7928),
    "reach-yz": ExplorationNoise(noise_std=2.4266, random_prob=0.8089),
    "reach-xyz": ExplorationNoise(noise_std=2.3459, random_prob=0.782),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

GOAL_LOW = np.array([-0.2, 0.45, 0.08])
GOAL_HIGH = np.array([0.2, 0.85, 0.35])
SUCCESS_RADIUS = 0.05
MIN_START_DISTANCE = 0.12


class ReachScene(SceneEnv):
    base_xml = "sawyer_xyz/sawyer_reach_v3.xml"

    def __init__(self, plane: str) -> None:
        self.free_axes = ["xyz".index(c) for c in plane]
        super().__init__()

    def edit_spec(self, spec) -> None:
        # Meta-World's reach scene carries an unused puck; the benchmark's reach has none.
        spec.detach_body(spec.body("obj"))
        spec.site("goal").delete()
        add_marker(spec, "goal")

    def _get_pos_objects(self) -> np.ndarray:
        return np.zeros(3)

    def _get_quat_objects(self) -> np.ndarray:
        return np.array([0.0, 0.0, 0.0, 1.0])

    def _sample_goal(self) -> np.ndarray:
        goal = self.hand_init_pos.copy()
        axes = self.free_axes
        goal[axes] = self.np_random.uniform(GOAL_LOW[axes], GOAL_HIGH[axes])
        return goal

    def reset_model(self) -> np.ndarray:
        self._reset_hand()
        goal = self._sample_goal()
        # Rejection keeps the goal away from the start so no episode is won at reset.
        while np.linalg.norm(goal - self.init_tcp) < MIN_START_DISTANCE:
            goal = self._sample_goal()
        self._target_pos = goal
        self.set_site("goal", goal)
        return self._get_obs()

    def evaluate_state(self, obs, action):
        distance = float(np.linalg.norm(self.tcp_center - self._target_pos))
        margin = float(np.linalg.norm(self.init_tcp - self._target_pos))
        in_place = reward_utils.tolerance(
            distance, bounds=(0, SUCCESS_RADIUS), margin=margin, sigmoid="long_tail"
        )
        return 10.0 * in_place, {"success": distance <= SUCCESS_RADIUS, "distance": distance}


class ReachOracle(Oracle):
    def action(self, s: State) -> np.ndarray:
        # One phase: fly the hand straight at the goal, gripper open.
        return pose_action(move(s.hand, s.goal, gain=10.0), -1.0)


for _plane in ("xy", "xz", "yz", "xyz"):
    _axes = {"xy": ("x", "y"), "xz": ("x", "z"), "yz": ("y", "z"), "xyz": ("x", "y", "z")}[_plane]
    register_task(
        TaskSpec(
            id=f"reach-{_plane}",
            title=f"reach in {_plane}" + (" (plane)" if len(_plane) == 2 else ""),
            instruction=(
                f"Move the gripper to the magenta marker; the marker varies in the {_plane} "
                + ("plane." if len(_plane) == 2 else "space.")
            ),
            success=f"gripper centre within {SUCCESS_RADIUS} m of the marker",
            scene=lambda p=_plane: ReachScene(p),
            oracle=ReachOracle,
            exploration=EXPLORATION[f"reach-{_plane}"],
            components={"action": tuple(f"move-{a}" for a in _axes), "perception": ("marker",)},
        )
    )
