"""ccdata: the six compositional task suites, their oracles, and their LeRobot datasets."""

import os as _os

# Headless rendering by default; a user's explicit choice wins.
_os.environ.setdefault("MUJOCO_GL", "egl")

from ccdata.env import TaskEnv, make_env, register_gym_ids  # noqa: E402
from ccdata.policies import make_policy  # noqa: E402
from ccdata.render import CAMERAS, RenderSettings  # noqa: E402
from ccdata.scoring import GAMMA, normalize  # noqa: E402
from ccdata.suites import SUITES, Suite, get_suite  # noqa: E402
from ccdata.tasks import TASKS, TaskSpec, get_task  # noqa: E402

register_gym_ids()

__all__ = [
    "CAMERAS",
    "GAMMA",
    "SUITES",
    "TASKS",
    "RenderSettings",
    "Suite",
    "TaskEnv",
    "TaskSpec",
    "get_suite",
    "get_task",
    "make_env",
    "make_policy",
    "normalize",
]
