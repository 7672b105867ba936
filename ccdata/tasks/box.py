"""Box scenes: Meta-World's box and lid (`sawyer_box.xml`), alone or with the benchmark cube.

`box-close` keeps Meta-World's box-close semantics: the lid lies on the table in front of the
box; grasp its handle and put it on the box (success: the lid within 0.08 m of a point 0.133 m
above the box's centre). `box-pnp-close` adds the cube: put the cube into the open box, then
close the lid over it.

Geometry (from `box.xml` / `boxtop.xml`, world frame, box body at (x, y, 0)): the box's inner
space spans +-0.09 m in x and y, its floor is at z = 0.01 and its rim at z = 0.06. The lid's
`top_link` (object 2, or object 1 in box-close) sits 0.016 m above the table when the lid lies
flat, and at z = 0.076 when the lid closes the box; its plate's underside is then 0.072 m
above the table, so the benchmark cube (0.04 m, resting at z = 0.01..0.05) fits under the
closed lid: no resizing needed. The handle bar runs along x, 0.082 m above `top_link`.
"""

from __future__ import annotations

import numpy as np
from metaworld.utils import reward_utils

from ccdata.policies.base import Oracle, State, move, pose_action
from ccdata.tasks.base import CUBE_HALF_SIZE, SceneEnv, add_cube, add_marker
from ccdata.tasks.drawer import carry_score
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "box-close": ExplorationNoise(noise_std=0.2006, random_prob=0.0669),
    "box-pnp-close": ExplorationNoise(noise_std=0.1175, random_prob=0.0392),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

LID_TARGET_Z = 0.133
"""Meta-World's lid target height above the box's centre."""
CLOSE_TOL = 0.08
"""Meta-World's box-close success threshold on the lid's distance to its target."""
LID_REST_Z = -0.058
"""Lid body height at which its skirt rests on the table (Meta-World drops it from 0.02)."""
LID_QUAT = (np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))
"""The lid's rest orientation (Meta-World's: 90 degrees about z, handle bar along x)."""
HANDLE_DZ = 0.082
"""Handle bar height above `top_link`."""
BOX_HALF = 0.1
LID_HALF = 0.115
INNER_HALF = 0.09
"""Half-extent of the box's inner space (walls excluded)."""
BOX_RIM_Z = 0.06
BOX_FLOOR_Z = 0.01
FOOTPRINT_GAP = 0.03
"""Minimum clearance between the footprints of box, lid and cube at reset."""

# Meta-World's box-close ranges (box centre, lid centre); the lid is always nearer the robot.
CLOSE_BOX_LOW, CLOSE_BOX_HIGH = (-0.1, 0.7), (0.1, 0.8)
CLOSE_LID_LOW, CLOSE_LID_HIGH = (-0.05, 0.5), (0.05, 0.55)
# box-pnp-close: lid and cube share the near row on opposite sides, the box is behind them.
PNP_BOX_LOW, PNP_BOX_HIGH = (-0.12, 0.74), (0.12, 0.8)
PNP_LID_X, PNP_LID_Y = (0.1, 0.22), (0.46, 0.52)
PNP_CUBE_X, PNP_CUBE_Y = (0.08, 0.2), (0.48, 0.6)


def footprints_clear(a_xy, a_half: float, b_xy, b_half: float) -> bool:
    """True when two axis-aligned square footprints are at least FOOTPRINT_GAP apart."""
    d = np.abs(np.asarray(a_xy) - np.asarray(b_xy))
    return bool(np.any(d >= a_half + b_half + FOOTPRINT_GAP))


class BoxScene(SceneEnv):
    """Meta-World's box and lid; with `with_cube`, the benchmark cube as well."""

    base_xml = "sawyer_xyz/sawyer_box.xml"

    def __init__(self, with_cube: bool) -> None:
        self.with_cube = with_cube
        super().__init__()

    def edit_spec(self, spec) -> None:
        spec.body("boxbodytop").joints[0].name = "lidjoint"
        spec.site("goal").delete()
        add_marker(spec, "goal")
        if self.with_cube:
            add_cube(spec)

    # --- state -------------------------------------------------------------------------------

    def lid_pos(self) -> np.ndarray:
        return self.data.body("top_link").xpos.copy()

    def _get_pos_objects(self) -> np.ndarray:
        if self.with_cube:
            return np.concatenate([self.data.body("cube").xpos, self.lid_pos()])
        return self.lid_pos()

    def _get_quat_objects(self) -> np.ndarray:
        lid = self.body_quat("top_link")
        if self.with_cube:
            return np.concatenate([self.body_quat("cube"), lid])
        return lid

    # --- layout ------------------------------------------------------------------------------

    def _sample_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        rng = self.np_random
        while True:
            if self.with_cube:
                box = rng.uniform(PNP_BOX_LOW, PNP_BOX_HIGH)
                side = rng.choice([-1.0, 1.0])
                lid = np.array([side * rng.uniform(*PNP_LID_X), rng.uniform(*PNP_LID_Y)])
                cube = np.array([-side * rng.uniform(*PNP_CUBE_X), rng.uniform(*PNP_CUBE_Y)])
                ok = footprints_clear(cube, CUBE_HALF_SIZE, lid, LID_HALF) and footprints_clear(
                    cube, CUBE_HALF_SIZE, box, BOX_HALF
                )
            else:
                box = rng.uniform(CLOSE_BOX_LOW, CLOSE_BOX_HIGH)
                lid = rng.uniform(CLOSE_LID_LOW, CLOSE_LID_HIGH)
                cube, ok = None, np.linalg.norm(box - lid) >= 0.25  # Meta-World's rejection
            if ok and footprints_clear(lid, LID_HALF, box, BOX_HALF):
                return box, lid, cube

    def reset_model(self) -> np.ndarray:
        box, lid, cube = self._sample_layout()
        # The box is part of the model, not of the state that mj_resetData clears: it moves
        # before the hand's reset steps, or those would run against the previous episode's box
        # and carry it into this one (through the solver's warm start).
        self.model.body("boxbody").pos = [box[0], box[1], 0.0]
        self._reset_hand()
        self.set_free_body("lidjoint", [lid[0], lid[1], LID_REST_Z], LID_QUAT)
        # goal (both tasks): Meta-World's lid target above the box's centre. In box-pnp-close
        # the cube's own target is straight below it, on the box's floor.
        self._target_pos = np.array([box[0], box[1], LID_TARGET_Z])
        self._cube_target = np.array([box[0], box[1], BOX_FLOOR_Z + CUBE_HALF_SIZE])
        if cube is not None:
            cube_pos = np.array([cube[0], cube[1], CUBE_HALF_SIZE])
            self.set_free_body("cubejoint", cube_pos)
            self.obj_init_pos = cube_pos
        else:
            self.obj_init_pos = np.array([lid[0], lid[1], LID_REST_Z])
        self.set_site("goal", self._target_pos)
        return self._get_obs()

    # --- scoring -----------------------------------------------------------------------------

    def close_error(self) -> float:
        return float(np.linalg.norm(self.lid_pos() - self._target_pos))

    def close_reward(self, action) -> float:
        """Meta-World box-close v2 shaping in [0, 10]: grasp the handle, set the lid on the box."""
        hand = self.tcp_center
        lid = self.lid_pos() + np.array([0.0, 0.0, 0.02])  # Meta-World's reference point
        grab = float(np.clip((action[3] + 1.0) / 2.0, 0.0, 1.0))
        near_handle = reward_utils.tolerance(
            float(np.linalg.norm(hand - lid)), bounds=(0, 0.02), margin=0.5, sigmoid="long_tail"
        )
        # Height error counts three times so the lid is lifted over the rim, not dragged.
        placed = reward_utils.tolerance(
            float(np.linalg.norm((self._target_pos - lid) * np.array([1.0, 1.0, 3.0]))),
            bounds=(0, 0.05),
            margin=0.25,
            sigmoid="long_tail",
        )
        lifted = 0.2 * float(lid[2] > 0.04) + 0.8 * placed
        reward = 2.0 * reward_utils.hamacher_product(grab, near_handle) + 8.0 * lifted
        # A tilted lid earns little (Meta-World's guard against flipping the lid onto the box).
        tilt = float(np.arccos(np.clip(self.data.body("top_link").xmat[8], -1.0, 1.0)))
        return reward * max(1.0 - tilt / 0.4, 0.0)

    def cube_in_box(self) -> bool:
        cube = self.data.body("cube").xpos
        box = self.model.body("boxbody").pos
        inside_xy = np.all(np.abs(cube[:2] - box[:2]) <= INNER_HALF - CUBE_HALF_SIZE)
        # "Below the rim": the whole cube, not just its centre.
        return bool(inside_xy and cube[2] + CUBE_HALF_SIZE <= BOX_RIM_Z)

    def evaluate_state(self, obs, action):
        closed = self.close_error() < CLOSE_TOL
        if not self.with_cube:
            reward = 10.0 if closed else self.close_reward(action)
            return reward, {"success": closed, "close_error": self.close_error()}
        inside = self.cube_in_box()
        success = closed and inside
        if success:
            reward = 10.0
        elif not inside:
            # Stage 1 in [0, 5]: carry the cube onto the box's floor.
            cube = self.data.body("cube").xpos
            reward = 5.0 * carry_score(self, action, cube, self._cube_target)
        else:
            # Stage 2 in [5, 10]: the box-close reward at half scale.
            reward = 5.0 + 0.5 * self.close_reward(action)
        return reward, {
            "success": success,
            "cube_in_box": inside,
            "lid_closed": closed,
            "close_error": self.close_error(),
        }


# --- oracles ---------------------------------------------------------------------------------

CARRY_Z = 0.25
"""Travel height: the carried lid (0.075 m below the hand) clears the box's rim."""
HANDLE_GRASP_DZ = HANDLE_DZ - 0.01
"""Hand height above `top_link` when closing on the handle bar."""
CUBE_GRASP_DZ = 0.03
"""Close on the cube once the hand is this close above its centre (the hand's floor)."""
CLOSE_STEPS = 6
"""Agent steps spent closing the fingers before lifting."""


class _Phases(Oracle):
    """Phase memory shared by the box oracles: which stage, and how long the fingers closed."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.stage = 0
        self.closing = 0
        self.opening = 0

    def grab(self, hand, grasp_point, carry_target_hand) -> np.ndarray | None:
        """Fly over `grasp_point`, descend, close, lift and carry the hand to the target.

        Returns None once the hand holds the object at `carry_target_hand`.
        """
        if self.closing < CLOSE_STEPS:
            if np.linalg.norm(hand[:2] - grasp_point[:2]) > 0.01:
                # Fly over the object at travel height.
                target = [grasp_point[0], grasp_point[1], CARRY_Z]
                return pose_action(move(hand, target), -1.0)
            if hand[2] - grasp_point[2] > 0.005:
                # Descend with the fingers open.
                return pose_action(move(hand, grasp_point), -1.0)
            # Close the fingers on it.
            self.closing += 1
            return pose_action(np.zeros(3), 1.0)
        if np.linalg.norm(hand[:2] - carry_target_hand[:2]) > 0.01:
            if hand[2] < CARRY_Z - 0.03:
                # Lift straight up first.
                return pose_action(move(hand, [hand[0], hand[1], CARRY_Z]), 1.0)
            # Carry at travel height.
            target = [carry_target_hand[0], carry_target_hand[1], CARRY_Z]
            return pose_action(move(hand, target), 1.0)
        if abs(hand[2] - carry_target_hand[2]) > 0.01:
            # Lower onto the target.
            return pose_action(move(hand, carry_target_hand), 1.0)
        return None


class BoxCloseOracle(_Phases):
    def action(self, s: State) -> np.ndarray:
        lid, goal = s.obj1, s.goal
        handle = lid + [0.0, 0.0, HANDLE_GRASP_DZ]
        # Hand position with the lid on the box (Meta-World counts lowering into range as done).
        over_box = goal + [0.0, 0.0, HANDLE_GRASP_DZ - 0.04]
        act = self.grab(s.hand, handle, over_box)
        return act if act is not None else pose_action(np.zeros(3), 1.0)


class BoxPnPCloseOracle(_Phases):
    """Put the cube in the box (stage 0), let go and rise (stage 1), then close the lid."""

    def action(self, s: State) -> np.ndarray:
        cube, lid, goal = s.obj1, s.obj2, s.goal
        if self.stage == 0:
            cube_target = np.array([goal[0], goal[1], BOX_FLOOR_Z + CUBE_HALF_SIZE])
            act = self.grab(
                s.hand, cube + [0.0, 0.0, CUBE_GRASP_DZ], cube_target + [0, 0, CUBE_GRASP_DZ]
            )
            if act is not None:
                return act
            self.stage, self.closing = 1, 0
        if self.stage == 1:
            if self.opening < CLOSE_STEPS:
                # Let go of the cube on the box's floor.
                self.opening += 1
                return pose_action(np.zeros(3), -1.0)
            if s.hand[2] < CARRY_Z - 0.03:
                # Rise clear of the box before fetching the lid.
                return pose_action(move(s.hand, [s.hand[0], s.hand[1], CARRY_Z]), -1.0)
            self.stage = 2
        handle = lid + [0.0, 0.0, HANDLE_GRASP_DZ]
        over_box = goal + [0.0, 0.0, HANDLE_GRASP_DZ - 0.04]
        act = self.grab(s.hand, handle, over_box)
        return act if act is not None else pose_action(np.zeros(3), 1.0)


register_task(
    TaskSpec(
        id="box-close",
        title="close box",
        instruction="Pick up the lid by its handle and put it on the box.",
        success=f"lid within {CLOSE_TOL} m of Meta-World's target above the box",
        scene=lambda: BoxScene(with_cube=False),
        oracle=BoxCloseOracle,
        exploration=EXPLORATION["box-close"],
        components={
            "action": ("reach-handle", "grasp", "lift", "transport", "lower-lid"),
            "perception": ("box",),
        },
    )
)
register_task(
    TaskSpec(
        id="box-pnp-close",
        title="pick and place cube inside box then close it",
        instruction="Put the green cube into the box, then close the box with its lid.",
        success=(
            "cube inside the box below its rim and the lid within "
            f"{CLOSE_TOL} m of its target above the box"
        ),
        scene=lambda: BoxScene(with_cube=True),
        oracle=BoxPnPCloseOracle,
        exploration=EXPLORATION["box-pnp-close"],
        components={
            "action": (
                "reach-object",
                "grasp",
                "lift",
                "transport",
                "release",
                "reach-handle",
                "lower-lid",
            ),
            "perception": ("box", "cube"),
        },
    )
)
