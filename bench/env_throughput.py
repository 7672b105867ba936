"""Agent steps/s with three 64 px cameras, versus Meta-World's own render() of the same views.

Prints JSON. Both paths step the same scene with the same seeded random actions; the baseline
renders the three views through Meta-World's MujocoEnv.render() at its default settings
(4096 shadow map, 4x MSAA, reflections, skybox), the benchmark through ccdata's renderer.
`render_ms` breaks one render down: milliseconds per camera at three image sizes, and at 64 px
with the arm's meshes (geom group 1) hidden, which tells what a frame's cost goes to.
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


def steps_per_second(env, steps: int, seed: int, after_step=None) -> float:
    """Agent steps/s under seeded random actions; `after_step` runs after every step."""
    rng = np.random.default_rng(seed)
    env.reset()
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 4))
        if after_step is not None:
            after_step()
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def benchmark_steps(task_id: str, steps: int, seed: int = 0) -> float:
    """The benchmark's own renderer: three 64 px cameras in every observation."""
    env = ccdata.make_env(task_id, seed=seed, image_size=64)
    rate = steps_per_second(env, steps, seed)
    env.close()
    return rate


def metaworld_render_steps(task_id: str, steps: int, seed: int = 0) -> float:
    """Physics without our cameras, plus Meta-World's MujocoEnv.render() of the same views."""
    env = ccdata.make_env(task_id, seed=seed, render=False)
    scene = env.scene
    scene.render_mode = "rgb_array"
    scene.mujoco_renderer = MujocoRenderer(scene.model, scene.data, width=64, height=64)
    camera = mujoco.mjtObj.mjOBJ_CAMERA
    cam_ids = [mujoco.mj_name2id(scene.model, camera, c) for c in ccdata.CAMERAS]

    def render_three_views() -> None:
        for cam in cam_ids:
            scene.mujoco_renderer.camera_id = cam
            scene.render()

    rate = steps_per_second(env, steps, seed, render_three_views)
    scene.mujoco_renderer.close()
    env.close()
    return rate


def render_ms(task_id: str, repeats: int = 30) -> dict:
    """Median ms per camera render (scene update + draw + read back), by image size, and at
    64 px with geom group 1 (the Sawyer's meshes) hidden."""

    def per_camera(size: int, hide_arm: bool) -> dict:
        env = ccdata.make_env(task_id, seed=0, image_size=size)
        env.reset()
        renderer, data = env._renderer._renderer, env.scene.data
        option = mujoco.MjvOption()
        option.geomgroup[1] = not hide_arm
        out = {}
        for camera in ccdata.CAMERAS:
            times = []
            for _ in range(repeats + 1):  # the first one warms up
                start = time.perf_counter()
                renderer.update_scene(data, camera=camera, scene_option=option)
                renderer.render()
                times.append(time.perf_counter() - start)
            out[camera] = round(1000 * statistics.median(times[1:]), 2)
        env.close()
        return out

    state_only = ccdata.make_env(task_id, seed=0, render=False)
    faces = int(state_only.scene.model.mesh_facenum.sum())
    state_only.close()
    return {
        **{f"{size}px": per_camera(size, False) for size in (16, 64, 256)},
        "64px_arm_meshes_hidden": per_camera(64, True),
        "mesh_faces": faces,
    }


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
    physics = steps_per_second(state_only, args.steps, seed=0)
    state_only.close()
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
        "render_ms": render_ms(args.task),
        "targets": {"agent_steps_per_s": 35, "speedup": 8},
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
