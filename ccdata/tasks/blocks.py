"""PnPBlock suite scenes: a red and a blue block (cube-sized) and a magenta goal on the table.

Each task builds its scene with only the blocks it uses, so a block that plays no part is
neither visible nor in the state. State slots: object 1 is the red block (or the only block),
object 2 the blue block (zeros when absent); the goal is the marker on the table.

- pnp-red-block / pnp-blue-block: put the one block at the marker.
- stack-blocks: put the red block at the marker, then the blue block on top of it.
"""

from __future__ import annotations

import numpy as np

from ccdata.policies.base import State
from ccdata.tasks.base import CUBE_HALF_SIZE, SceneEnv, add_free_box, add_marker
from ccdata.tasks.grasp import (
    PLACE_RADIUS,
    REST_Z,
    START_HIGH,
    START_LOW,
    TABLE_HIGH,
    TABLE_LOW,
    PickPlaceOracle,
    pads_touch,
    sample_xy,
    transport_reward,
)
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "pnp-red-block": ExplorationNoise(noise_std=0.6834, random_prob=0.2278),
    "pnp-blue-block": ExplorationNoise(noise_std=0.6834, random_prob=0.2278),
    "stack-blocks": ExplorationNoise(noise_std=0.3347, random_prob=0.1116),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

BLOCK_RGBA = {"red": (0.85, 0.1, 0.1, 1.0), "blue": (0.1, 0.2, 0.9, 1.0)}
"""Block colours; neither is the cube's green nor the goal's magenta."""
BLOCK_SEPARATION = 0.12
"""Minimum xy distance between any two of the blocks' starts and the goal."""
STACK_GOAL_RADIUS = 0.05
"""Stack stage 1: red block's xy distance to the goal."""
STACK_XY_TOLERANCE = 0.025
"""Stack stage 2: blue block's xy distance to the red block."""
STACK_Z_TOLERANCE = 0.01
"""How far a block's bottom may be from what it rests on (table or red block)."""
STACK_HEIGHT = 2 * CUBE_HALF_SIZE
"""Centre-to-centre height of the blue block resting on the red one."""
PLACED_NOT_RELEASED = 8.0
"""Stack stage shaping (of 10) for a block already in place but still in the gripper."""


def block_name(colour: str) -> str:
    return f"{colour}_block"


class BlockScene(SceneEnv):
    base_xml = "sawyer_xyz/sawyer_pick_place_v3.xml"

    def __init__(self, colours: tuple[str, ...], stack: bool = False) -> None:
        unknown = [c for c in colours if c not in BLOCK_RGBA]
        if unknown or not colours:
            raise ValueError(f"block colours {colours!r}: choose from {tuple(BLOCK_RGBA)}")
        if stack and colours != ("red", "blue"):
            raise ValueError(f"stacking needs colours ('red', 'blue'), got {colours!r}")
        self.colours = colours
        self.stack = stack
        self.geoms = [block_name(c) + "Geom" for c in colours]
        super().__init__()

    def edit_spec(self, spec) -> None:
        spec.detach_body(spec.body("obj"))
        spec.site("goal").delete()
        for i, colour in enumerate(self.colours):
            name = block_name(colour)
            add_free_box(spec, name, CUBE_HALF_SIZE, BLOCK_RGBA[colour], pos=(0.1 * i, 0.6, REST_Z))
        add_marker(spec, "goal")

    def _get_id_main_object(self) -> int:
        return self.data.geom(self.geoms[0]).id

    def _get_pos_objects(self) -> np.ndarray:
        return np.concatenate([self.data.body(block_name(c)).xpos for c in self.colours])

    def _get_quat_objects(self) -> np.ndarray:
        return np.concatenate([self.body_quat(block_name(c)) for c in self.colours])

    def reset_model(self) -> np.ndarray:
        rng = self.np_random
        self.hand_init_pos = np.array(self.hand_init)
        self._reset_hand()
        starts: list[np.ndarray] = []
        for colour in self.colours:
            xy = sample_xy(rng, START_LOW, START_HIGH, starts, BLOCK_SEPARATION)
            starts.append(np.array([*xy, REST_Z]))
            self.set_free_body(block_name(colour) + "joint", starts[-1])
        goal_xy = sample_xy(rng, TABLE_LOW, TABLE_HIGH, starts, BLOCK_SEPARATION)
        self._starts = [p.copy() for p in starts]
        self._target_pos = np.array([*goal_xy, REST_Z])
        self.set_site("goal", self._target_pos)
        return self._get_obs()

    # --- scoring ------------------------------------------------------------------------------

    def _released(self, *geoms: str) -> bool:
        return not any(pads_touch(self, self.data.geom(g).id) for g in geoms)

    def red_at_goal(self, red: np.ndarray) -> bool:
        """The red block rests on the table at the goal (held or not)."""
        return bool(
            np.linalg.norm(red[:2] - self._target_pos[:2]) <= STACK_GOAL_RADIUS
            and abs(red[2] - REST_Z) <= STACK_Z_TOLERANCE
        )

    def blue_on_red(self, red: np.ndarray, blue: np.ndarray) -> bool:
        """The blue block rests on the red one (held or not)."""
        return bool(
            np.linalg.norm(blue[:2] - red[:2]) <= STACK_XY_TOLERANCE
            and abs(blue[2] - red[2] - STACK_HEIGHT) <= STACK_Z_TOLERANCE
        )

    def evaluate_state(self, obs, action):
        first = obs[4:7]
        goal = self._target_pos
        if not self.stack:
            distance = float(np.linalg.norm(first - goal))
            success = distance <= PLACE_RADIUS
            if success:
                reward = 10.0
            else:
                reward = transport_reward(
                    self, action, self.geoms[0], first, self._starts[0], goal, PLACE_RADIUS
                )
            return reward, {"success": bool(success), "distance": distance}
        red, blue = first, obs[11:14]
        red_geom, blue_geom = self.geoms
        # Stage 1 is done once the red block sits at the goal and the gripper has let it go.
        stage_one = self.red_at_goal(red) and self._released(red_geom)
        success = stage_one and self.blue_on_red(red, blue) and self._released(blue_geom)
        if success:
            reward = 10.0
        elif not stage_one:
            # Stage 1 maps into [0, 5]; a block set down but still held earns 4 of them.
            shaped = transport_reward(
                self, action, red_geom, red, self._starts[0], goal, STACK_GOAL_RADIUS
            )
            if self.red_at_goal(red):
                shaped = max(shaped, PLACED_NOT_RELEASED)
            reward = 0.5 * shaped
        else:
            # Stage 2 maps into [5, 10], the same way.
            on_red = red + np.array([0.0, 0.0, STACK_HEIGHT])
            shaped = transport_reward(
                self, action, blue_geom, blue, self._starts[1], on_red, STACK_XY_TOLERANCE
            )
            if self.blue_on_red(red, blue):
                shaped = max(shaped, PLACED_NOT_RELEASED)
            reward = 5.0 + 0.5 * shaped
        return reward, {"success": bool(success), "stage": 1 + int(stage_one)}


# --- oracles ------------------------------------------------------------------------------------


class BlockOracle(PickPlaceOracle):
    """Grasp the only block, carry it above the marker, set it down, let go."""


class StackOracle(PickPlaceOracle):
    """Two pick-and-place stages: red block to the goal, then blue block onto the red one."""

    def reset(self) -> None:
        super().reset()
        self.stage = "red"

    def action(self, s: State) -> np.ndarray:
        tcp_z = s.hand[2]
        if self.stage == "red":
            # Stage 1 ends once the red block is let go and the hand has backed off above it.
            if self.phase == "retreat" and tcp_z > s.obj1[2] + 0.12:
                self.stage = "blue"
                super().reset()
            else:
                return self.step(s, s.obj1, s.goal)
        # Stage 2: the blue block goes onto wherever the red block now is.
        on_red = s.obj1 + np.array([0.0, 0.0, STACK_HEIGHT + 0.002])
        return self.step(s, s.obj2, on_red)


PNP_ACTIONS = ("reach-object", "grasp", "lift", "transport", "release")

for _colour in ("red", "blue"):
    register_task(
        TaskSpec(
            id=f"pnp-{_colour}-block",
            title=f"pick and place {_colour} block",
            instruction=f"Pick up the {_colour} block and place it on the magenta marker.",
            success=f"{_colour} block centre within {PLACE_RADIUS} m of the marker",
            scene=lambda c=_colour: BlockScene((c,)),
            oracle=BlockOracle,
            exploration=EXPLORATION[f"pnp-{_colour}-block"],
            components={"action": PNP_ACTIONS, "perception": (f"{_colour}-block",)},
        )
    )

register_task(
    TaskSpec(
        id="stack-blocks",
        title="stack the two blocks",
        instruction=(
            "Place the red block on the magenta marker, then stack the blue block on top of it."
        ),
        success=(
            f"red block on the table within {STACK_GOAL_RADIUS} m (xy) of the marker; blue "
            f"block resting on it (xy within {STACK_XY_TOLERANCE} m, bottom within "
            f"{STACK_Z_TOLERANCE} m of the red block's top); neither block in the gripper"
        ),
        scene=lambda: BlockScene(("red", "blue"), stack=True),
        oracle=StackOracle,
        exploration=EXPLORATION["stack-blocks"],
        components={"action": (*PNP_ACTIONS, "stack"), "perception": ("red-block", "blue-block")},
    )
)
