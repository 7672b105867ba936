"""Drawer scenes: Meta-World's drawer (`sawyer_drawer.xml`), alone or beside the benchmark cube.

`drawer-open` keeps Meta-World's drawer-open semantics: the drawer stands at the back of the
table at a random x, the hand hooks the handle and pulls until the handle is within 0.03 m of
a point 0.2 m in front of where it started (the slide's limit is 0.16 m, so this means
"pulled out all the way"). `drawer-pnp` adds the cube beside the drawer: open the drawer,
then put the cube inside it.

Geometry used below (from `drawer.xml`, world frame, drawer body at (x, y, 0)):
the sliding `drawer_link` sits at (x, y - 0.01, 0.09) when closed and slides 0.16 m towards
the robot (-y). Its inner box spans +-0.084 m in x and +-0.074 m in y around the link's
origin, with the floor at z = 0.046 and the rim at z = 0.15. The handle bar runs along x
0.15 m in front of the link's origin at the link's height; Meta-World's "handle" point
(object 1 in drawer-open) is the link's origin moved 0.16 m towards the robot.
"""

from __future__ import annotations

import numpy as np
from metaworld.utils import reward_utils

from ccdata.policies.base import Oracle, State, move, pose_action
from ccdata.tasks.base import CUBE_HALF_SIZE, SceneEnv, add_cube, add_marker
from ccdata.tasks.grasp import transport_reward
from ccdata.tasks.registry import ExplorationNoise, TaskSpec, register_task

EXPLORATION: dict[str, ExplorationNoise] = {
    "drawer-open": ExplorationNoise(noise_std=0.5725, random_prob=0.1908),
    "drawer-pnp": ExplorationNoise(noise_std=0.1758, random_prob=0.0586),
}
"""Calibrated noisy-oracle noise per task (`ccdata calibrate`): about half of the noisy-oracle
episodes succeed."""

DRAWER_Y = 0.9
"""Meta-World keeps the drawer body at y = 0.9 and randomises only x."""
OPEN_X_RANGE = (-0.1, 0.1)
"""Drawer x range in drawer-open (Meta-World's)."""
PULL_DIST = 0.2
"""Meta-World's target: the handle 0.2 m in front of its closed position (and 0.09 up)."""
OPEN_TOL = 0.03
"""Meta-World's drawer-open success threshold on the handle's distance to the target."""
SETTLED_SLACK = 0.01
"""drawer-pnp: extra slack on OPEN_TOL. The slide's limit (0.16 m) leaves the handle exactly
0.03 m from the target, so a released drawer, which settles a few mm short of the limit, would fail
Meta-World's threshold; 1 cm keeps "fully pulled out and let go" open."""
HANDLE_OFFSET = np.array([0.0, -0.16, 0.0])
"""Meta-World's handle point relative to the `drawer_link` origin."""
LINK_TO_PLACE = np.array([0.0, -0.03, -0.044 + CUBE_HALF_SIZE])
"""From the link's origin to the cube's resting place on the drawer's floor: 3 cm in front of
the floor's centre, so the hand lowering it stays clear of the drawer case's top."""
INNER_HALF_XY = np.array([0.084, 0.074])
"""Half-extent of the drawer's inner box (walls excluded) around the link's origin."""
RIM_DZ = 0.06
"""Height of the drawer's rim above the link's origin."""
CUBE_X_GAP = (0.2, 0.28)
"""drawer-pnp: cube's x distance from the drawer centre (drawer + case half-width is 0.118)."""
CUBE_Y_RANGE = (0.5, 0.68)
"""drawer-pnp: cube's y range, in front of the drawer's case (its front face is at y = 0.8)."""
PNP_DRAWER_X = (0.05, 0.2)
"""drawer-pnp: |x| of the drawer; the cube goes on the other side of the table's centre."""
PLACE_RADIUS = 0.05
"""Meta-World pick-place's target radius, used to shape the carry part of the reward."""

DRAWER_RGBA = (0.62, 0.5, 0.36, 1.0)
"""Meta-World paints the drawer green; the benchmark's cube is green, so the drawer is wood."""
DRAWER_MATERIALS = ("drawer_beige", "drawer_red")


def carry_score(scene: SceneEnv, action, obj: np.ndarray, target: np.ndarray) -> float:
    """The cube's pick-and-place shaping (`grasp.transport_reward`) scaled to [0, 1]: 7 is the
    most it gives before success (caging x closeness 1, held bonus 1 + 5)."""
    shaped = transport_reward(
        scene, action, "cubeGeom", obj, scene.obj_init_pos, target, PLACE_RADIUS
    )
    return float(np.clip(shaped / 7.0, 0.0, 1.0))


class DrawerScene(SceneEnv):
    """Meta-World's drawer; with `with_cube`, the benchmark cube stands beside it."""

    base_xml = "sawyer_xyz/sawyer_drawer.xml"

    def __init__(self, with_cube: bool) -> None:
        self.with_cube = with_cube
        super().__init__()

    def edit_spec(self, spec) -> None:
        for name in DRAWER_MATERIALS:
            spec.material(name).rgba = list(DRAWER_RGBA)
        spec.site("goal").delete()
        add_marker(spec, "goal")
        if self.with_cube:
            add_cube(spec)

    # --- state -------------------------------------------------------------------------------

    def handle_pos(self) -> np.ndarray:
        return self.data.body("drawer_link").xpos + HANDLE_OFFSET

    def _get_pos_objects(self) -> np.ndarray:
        if self.with_cube:
            return np.concatenate([self.data.body("cube").xpos, self.handle_pos()])
        return self.handle_pos()

    def _get_quat_objects(self) -> np.ndarray:
        drawer = self.body_quat("drawer_link")
        if self.with_cube:
            return np.concatenate([self.body_quat("cube"), drawer])
        return drawer

    # --- layout ------------------------------------------------------------------------------

    def reset_model(self) -> np.ndarray:
        self._reset_hand()
        rng = self.np_random
        if self.with_cube:
            side = rng.choice([-1.0, 1.0])
            drawer_x = side * rng.uniform(*PNP_DRAWER_X)
            cube_x = drawer_x - side * rng.uniform(*CUBE_X_GAP)
            cube = np.array([cube_x, rng.uniform(*CUBE_Y_RANGE), CUBE_HALF_SIZE])
        else:
            drawer_x = rng.uniform(*OPEN_X_RANGE)
        drawer = np.array([drawer_x, DRAWER_Y, 0.0])
        self.model.body("drawer").pos = drawer
        # Closed handle at drawer + (0, -0.17, 0.09); Meta-World's target is 0.2 m further out.
        self._open_target = drawer + np.array([0.0, -0.16 - PULL_DIST, 0.09])
        self._handle_init = self._open_target + np.array([0.0, PULL_DIST, 0.0])
        if self.with_cube:
            self.set_free_body("cubejoint", cube)
            self.obj_init_pos = cube
            # goal (drawer-pnp): where the cube should rest on the fully opened drawer's floor.
            link_open = drawer + np.array([0.0, -0.01 - 0.16, 0.09])
            self._target_pos = link_open + LINK_TO_PLACE
        else:
            self.obj_init_pos = self._handle_init
            # goal (drawer-open): Meta-World's handle target, 0.2 m in front of the closed handle.
            self._target_pos = self._open_target
        self.set_site("goal", self._target_pos)
        return self._get_obs()

    # --- scoring -----------------------------------------------------------------------------

    def open_error(self) -> float:
        return float(np.linalg.norm(self.handle_pos() - self._open_target))

    def open_reward(self) -> float:
        """Meta-World drawer-open v2 shaping in [0, 10]: hook the handle, pull it out."""
        handle = self.handle_pos()
        opening = reward_utils.tolerance(
            self.open_error(), bounds=(0, 0.02), margin=PULL_DIST, sigmoid="long_tail"
        )
        # x/y weighted so the hand lines up over the handle before it drops onto it.
        scale = np.array([3.0, 3.0, 1.0])
        reach = reward_utils.tolerance(
            float(np.linalg.norm((handle - self.tcp_center) * scale)),
            bounds=(0, 0.01),
            margin=float(np.linalg.norm((self._handle_init - self.init_tcp) * scale)),
            sigmoid="long_tail",
        )
        return 5.0 * (reach + opening)

    def cube_in_drawer(self) -> bool:
        cube = self.data.body("cube").xpos
        link = self.data.body("drawer_link").xpos
        inside_xy = np.all(np.abs(cube[:2] - link[:2]) <= INNER_HALF_XY - CUBE_HALF_SIZE)
        # "Below the rim": the whole cube, not just its centre.
        return bool(inside_xy and cube[2] + CUBE_HALF_SIZE <= link[2] + RIM_DZ)

    def evaluate_state(self, obs, action):
        if not self.with_cube:
            success = self.open_error() <= OPEN_TOL
            reward = 10.0 if success else self.open_reward()
            return reward, {"success": success, "open_error": self.open_error()}
        opened = self.open_error() <= OPEN_TOL + SETTLED_SLACK
        inside = self.cube_in_drawer()
        success = opened and inside
        if success:
            reward = 10.0
        elif not opened:
            # Stage 1 in [0, 5]: the drawer-open reward at half scale.
            reward = 0.5 * self.open_reward()
        else:
            # Stage 2 in [5, 10]: carry the cube to the floor of the open drawer.
            link = self.data.body("drawer_link").xpos
            target = link + LINK_TO_PLACE
            reward = 5.0 + 5.0 * carry_score(self, action, self.data.body("cube").xpos, target)
        return reward, {
            "success": success,
            "drawer_open": opened,
            "cube_in_drawer": inside,
            "open_error": self.open_error(),
        }


# --- oracles ---------------------------------------------------------------------------------

HOOK_DZ = -0.02
"""Hand height relative to the handle point when pulling: the open +y finger hangs behind the
handle bar, the other in front of it."""
ABOVE = 0.12
"""Clearance (m) above the handle or the cube when lining up."""
CARRY_Z = 0.25
"""Carry height: above the drawer's case (top at z = 0.17) with the cube hanging below."""
HANDLE_TO_LINK = -HANDLE_OFFSET
OPEN_MARGIN = 0.008
"""drawer-pnp oracle: the drawer counts as pulled out within 8 mm of the slide's limit."""
GRASP_DZ = 0.03
"""Close the fingers once the hand is this far above the cube's centre (the hand cannot go
lower on the table: its lowest point is ~0.046 m, the cube's centre is at 0.02 m)."""


def open_drawer_action(
    hand: np.ndarray, handle: np.ndarray, stop_y: float | None = None
) -> np.ndarray:
    """Meta-World-style pull: line up above the handle, drop onto it, drag it towards the robot.

    Without `stop_y` the pull runs at full speed into the slide's limit (Meta-World's target
    is only reached there). With `stop_y` the hand eases in to that handle y: a drawer slammed
    into its limit rebounds several cm once the hand lets go.
    """
    hook = handle + np.array([0.0, 0.0, HOOK_DZ])
    d = hand - hook
    if abs(d[0]) < 0.02 and -0.05 < d[1] < 0.015 and abs(d[2]) < 0.02:
        # Hooked (the hand leads the handle a little while pulling): pull straight out.
        if stop_y is None:
            return pose_action(move(hand, hook + [0.0, -0.1, 0.0], gain=50.0), -1.0)
        return pose_action(move(hand, [hook[0], stop_y + d[1], hook[2]], gain=8.0), -1.0)
    aligned = np.linalg.norm(d[:2]) < 0.015
    if not aligned and d[2] < 0.05:
        # Low but off the handle: rise first so the fingers clear the drawer.
        return pose_action(move(hand, [hand[0], hand[1], hook[2] + ABOVE]), -1.0)
    if not aligned:
        # Line up over the handle.
        return pose_action(move(hand, hook + [0.0, 0.0, ABOVE]), -1.0)
    # Drop down onto the handle.
    return pose_action(move(hand, hook), -1.0)


class DrawerOpenOracle(Oracle):
    def action(self, s: State) -> np.ndarray:
        return open_drawer_action(s.hand, s.obj1)


class DrawerPnPOracle(Oracle):
    """Open the drawer, then pick the cube and set it on the drawer's floor."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.opened = False
        self.rising = True
        self.grasped = False

    def action(self, s: State) -> np.ndarray:
        cube, handle = s.obj1, s.obj2
        target = handle + HANDLE_TO_LINK + LINK_TO_PLACE
        # Stage 1 until the drawer has been pulled out to its limit (remembered).
        if not self.opened:
            # The goal sits above the open drawer's floor, so the open handle is at goal y - 0.16.
            open_y = s.goal[1] - LINK_TO_PLACE[1] + HANDLE_OFFSET[1]
            if handle[1] > open_y + OPEN_MARGIN:
                return open_drawer_action(s.hand, handle, stop_y=open_y + OPEN_MARGIN / 2)
            self.opened = True
        to_cube = cube - s.hand
        if not self.grasped:
            if self.rising and s.hand[2] < CARRY_Z - 0.03:
                # Leave the handle straight up, clear of the drawer, before travelling.
                return pose_action(move(s.hand, [s.hand[0], s.hand[1], CARRY_Z]), -1.0)
            self.rising = False
            if np.linalg.norm(to_cube[:2]) > 0.01:
                # Fly over to the cube at carry height, clear of the open drawer's walls.
                return pose_action(move(s.hand, [cube[0], cube[1], CARRY_Z]), -1.0)
            if -to_cube[2] > GRASP_DZ:
                # Descend around the cube, fingers open.
                return pose_action(move(s.hand, cube), -1.0)
            # Close and wait until the fingers have closed on the cube.
            if s.gripper_open > 0.45:
                return pose_action(np.zeros(3), 1.0)
            self.grasped = True
        if np.linalg.norm(to_cube) > 0.04:
            # Lost the cube: go back for it.
            self.grasped = False
            return pose_action(move(s.hand, s.hand + [0.0, 0.0, 0.1]), -1.0)
        above_target = np.array([target[0], target[1], CARRY_Z])
        if np.linalg.norm(cube[:2] - target[:2]) > 0.015:
            if cube[2] < CARRY_Z - 0.05:
                # Lift clear of the drawer first.
                return pose_action(move(s.hand, [s.hand[0], s.hand[1], CARRY_Z + 0.02]), 1.0)
            # Carry over the drawer.
            return pose_action(move(s.hand, s.hand + (above_target - cube)), 1.0)
        # Lower the cube onto the drawer's floor.
        return pose_action(move(s.hand, s.hand + (target - cube)), 1.0)


register_task(
    TaskSpec(
        id="drawer-open",
        title="open drawer",
        instruction="Pull the drawer's handle until the drawer is fully open.",
        success=f"handle within {OPEN_TOL} m of Meta-World's open target (drawer pulled out)",
        scene=lambda: DrawerScene(with_cube=False),
        oracle=DrawerOpenOracle,
        exploration=EXPLORATION["drawer-open"],
        components={"action": ("reach-handle", "pull"), "perception": ("drawer",)},
    )
)
register_task(
    TaskSpec(
        id="drawer-pnp",
        title="open drawer then pick and place cube inside",
        instruction="Open the drawer, then pick up the green cube and place it inside the drawer.",
        success=(
            f"drawer open (handle within {OPEN_TOL + SETTLED_SLACK} m of the open target) and "
            "the cube inside the drawer's inner box, below its rim"
        ),
        scene=lambda: DrawerScene(with_cube=True),
        oracle=DrawerPnPOracle,
        exploration=EXPLORATION["drawer-pnp"],
        components={
            "action": (
                "reach-handle",
                "pull",
                "reach-object",
                "grasp",
                "lift",
                "transport",
                "release",
            ),
            "perception": ("drawer", "cube"),
        },
    )
)
