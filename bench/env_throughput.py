"""Agent steps/s with three 64 px cameras, versus Meta-World's own render() of the same views.

Prints JSON. Both paths step the same scene with the same seeded random actions; the baseline
renders the three views through Meta-World's MujocoEnv.render() at its default settings
(4096 shadow map, 4x MSAA, reflections, skybox), the benchmark through ccdata's renderer.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer  # noqa: E402

import ccdata  # noqa: E402


def benchmark_steps(task_id: str, steps: int, seed: int = 0) -> float:
    env = ccdata.make_env(task_id, seed=seed, image_size=64)
    rng = np.random.default_rng(seed)
    env.reset()
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 4))
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    env.close()
    return rate


def metaworld_render_steps(task_id: str, steps: int, seed: int = 0) -> float:
    env = ccdata.make_env(task_id, seed=seed, render=False)
    scene = env.scene
    scene.render_mode = "rgb_array"
    scene.mujoco_renderer = MujocoRenderer(scene.model, scene.data, width=64, height=64)
    camera = mujoco.mjtObj.mjOBJ_CAMERA
    cam_ids = [mujoco.mj_name2id(scene.model, camera, c) for c in ccdata.CAMERAS]
    rng = np.random.default_rng(seed)
    env.reset()
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 4))
        for cam in cam_ids:
            scene.mujoco_renderer.camera_id = cam
            scene.render()
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    scene.mujoco_renderer.close()
    env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", default="reach-xyz")
    parser.add_argument("--steps", type=int, default=250)
    parser.add_argument("--baseline-steps", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    ours = [benchmark_steps(args.task, args.steps) for _ in range(args.repeats)]
    theirs = [metaworld_render_steps(args.task, args.baseline_steps) for _ in range(args.repeats)]
    state_only = ccdata.make_env(args.task, seed=0, render=False)
    state_only.reset()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        _, _, te, tr, _ = state_only.step(np.zeros(4, np.float32))
        if te or tr:
            state_only.reset()
    physics = args.steps / (time.perf_counter() - t0)
    result = {
        "task": args.task,
        "cameras": list(ccdata.CAMERAS),
        "image_size": 64,
        "render_settings": ccdata.RenderSettings().to_dict(),
        "agent_steps_per_s_median": statistics.median(ours),
        "agent_steps_per_s_runs": ours,
        "metaworld_render_steps_per_s_median": statistics.median(theirs),
        "metaworld_render_steps_per_s_runs": theirs,
        "speedup_vs_metaworld_render": statistics.median(ours) / statistics.median(theirs),
        "state_only_agent_steps_per_s": physics,
        "targets": {"agent_steps_per_s": 35, "speedup": 8},
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
