"""`ccdata generate` throughput: end-to-end frames/s versus env-only steps/s, and 1 -> 2 workers.

Prints JSON. The env-only baseline replays exactly the generated plan (same tasks, policies,
seeds, rendering) without writing anything, so the ratio isolates the cost of recording.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from ccdata.env import EPISODE_STEPS, make_env  # noqa: E402
from ccdata.policies import make_policy  # noqa: E402
from ccdata.record import GenerateConfig, generate, plan, policy_seed  # noqa: E402


def env_only_rate(config: GenerateConfig) -> tuple[float, int]:
    """Steps/s of rolling out the plan with cameras on, writing nothing."""
    frames = 0
    start = time.perf_counter()
    env, env_task = None, None
    for spec in plan(config):
        if env_task != spec.task_id:
            if env is not None:
                env.close()
            env, env_task = (
                make_env(spec.task_id, render_settings=config.render_settings),
                spec.task_id,
            )
        policy = make_policy(
            spec.policy,
            spec.task_id,
            seed=policy_seed(spec.seed),
            noise_std=config.noise_std,
            random_prob=config.random_prob,
        )
        policy.reset()
        obs, _ = env.reset(seed=spec.seed)
        for _ in range(config.max_steps or EPISODE_STEPS):
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            frames += 1
            if terminated or truncated:
                break
    env.close()
    return frames / (time.perf_counter() - start), frames


def dir_bytes(root: Path, sub: str) -> int:
    return sum(p.stat().st_size for p in (root / sub).rglob("*") if p.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--suite", default="Grasp")
    # The default dataset's 2:1:1 mix of oracle, noisy-oracle and random episodes.
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--explore-episodes", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        results = {}
        for workers in (1, 2):
            config = GenerateConfig(
                suite=args.suite,
                episodes=args.episodes,
                explore_episodes=args.explore_episodes,
                workers=workers,
                root=Path(tmp) / f"w{workers}",
            )
            start = time.perf_counter()
            root, summary = generate(config, progress=False)
            wall = time.perf_counter() - start
            results[workers] = {
                "frames": summary["frames"],
                "wall_s": wall,
                "frames_per_s": summary["frames"] / wall,
            }
        env_rate, env_frames = env_only_rate(config)
        root = Path(tmp) / "w1"
        video, data = dir_bytes(root, "videos"), dir_bytes(root, "data")
    one = results[1]
    print(
        json.dumps(
            {
                "suite": args.suite,
                "episodes": {
                    "oracle": args.episodes,
                    "noisy-oracle": args.explore_episodes,
                    "random": args.explore_episodes,
                },
                "frames": one["frames"],
                "generate_frames_per_s_1_worker": one["frames_per_s"],
                "env_only_steps_per_s": env_rate,
                "ratio_generate_to_env_only": one["frames_per_s"] / env_rate,
                "generate_frames_per_s_2_workers": results[2]["frames_per_s"],
                "scaling_1_to_2_workers": results[2]["frames_per_s"] / one["frames_per_s"],
                "video_bytes_per_1000_frames": 1000 * video / one["frames"],
                "data_bytes_per_1000_frames": 1000 * data / one["frames"],
                "env_only_frames": env_frames,
                "targets": {"ratio_generate_to_env_only": 0.7},
                "cpu_count": os.cpu_count(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
