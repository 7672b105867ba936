"""`ccdata generate` throughput: end-to-end steps/s versus env-only steps/s, and 1 -> 2 workers.

Prints JSON. The env-only baseline replays exactly the generated plan (same tasks, policies,
seeds, noise, rendering) without writing anything, so the ratio isolates the cost of recording.
Each repeat runs 1 worker, 2 workers and env-only back to back and its ratios are computed
within the repeat, so that a machine shared with other work biases them as little as possible.
Each generation runs in a fresh interpreter, as `ccdata generate` does: no fork server warmed
by an earlier generation (`ccdata.processes`). Its cores busy count every process it started
(Linux: this script becomes their subreaper, so their CPU time reaches it).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from ccdata.env import make_env  # noqa: E402
from ccdata.episode_plan import plan  # noqa: E402
from ccdata.record import GenerateConfig  # noqa: E402
from ccdata.writer import episode_policy  # noqa: E402


def env_only_rate(config: GenerateConfig) -> tuple[float, int, float]:
    """Steps/s of rolling out the plan with cameras on, writing nothing; also the frames and
    the cores it kept busy (CPU seconds of all its threads per wall second)."""
    frames = 0
    start, cpu = time.perf_counter(), time.process_time()
    env, env_task = None, None
    for spec in plan(config):
        if env_task != spec.task_id:
            if env is not None:
                env.close()
            env, env_task = (
                make_env(
                    spec.task_id,
                    render_settings=config.render_settings,
                    episode_steps=config.episode_steps,
                ),
                spec.task_id,
            )
        policy = episode_policy(spec, config)
        obs, _ = env.reset(seed=spec.seed)
        for _ in range(config.max_steps or config.episode_steps):
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            frames += 1
            if terminated or truncated:
                break
    env.close()
    wall = time.perf_counter() - start
    return frames / wall, frames, (time.process_time() - cpu) / wall


GENERATE = """
import json, sys
from ccdata.record import GenerateConfig, generate
if __name__ == "__main__":
    config = GenerateConfig(**json.loads(sys.argv[1]))
    print(json.dumps(generate(config, progress=False)[1]))
"""


def generate_rate(args, workers: int, root: Path) -> tuple[float, int, float]:
    """Steps/s of a one-shot `generate` (end to end, merge included), the steps, and the cores
    it kept busy (all its processes)."""
    config = dict(
        suite=args.suite,
        episodes=args.episodes,
        explore_episodes=args.explore_episodes,
        workers=workers,
        root=str(root),
    )
    start, cpu = time.perf_counter(), _children_cpu_seconds()
    done = subprocess.run([sys.executable, "-c", GENERATE, json.dumps(config)],
                          capture_output=True, text=True, check=True)  # fmt: skip
    wall = time.perf_counter() - start
    _reap_orphans()
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    return summary["steps"] / wall, summary["steps"], (_children_cpu_seconds() - cpu) / wall


def _become_subreaper() -> None:
    """Orphans of our children (the fork server and what it forked outlive the generating
    process by moments) are reparented to us, so that waiting for them adds their CPU time."""
    if not sys.platform.startswith("linux"):
        sys.exit(
            "bench/dataset_write.py counts its generations' CPU through Linux's "
            "PR_SET_CHILD_SUBREAPER"
        )
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(36, 1) != 0:  # PR_SET_CHILD_SUBREAPER
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")


def _reap_orphans() -> None:
    while True:
        try:
            os.waitpid(-1, 0)
        except ChildProcessError:
            return


def _children_cpu_seconds() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return children.ru_utime + children.ru_stime


def dir_bytes(root: Path, sub: str) -> int:
    return sum(p.stat().st_size for p in (root / sub).rglob("*") if p.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--suite", default="Grasp")
    # The default dataset's 2:1:1 mix of oracle, noisy-oracle and random episodes.
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--explore-episodes", type=int, default=2)
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="rounds of (1 worker, 2 workers, env-only); medians are reported",
    )
    args = parser.parse_args()
    _become_subreaper()
    rates: dict[str, list[float]] = {
        "w1": [],
        "w2": [],
        "env": [],
        "env_cores": [],
        "w1_cores": [],
        "w2_cores": [],
    }
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for workers in (1, 2):
                root = Path(tmp) / f"r{r}-w{workers}"
                rate, frames, cores = generate_rate(args, workers, root)
                rates[f"w{workers}"].append(rate)
                rates[f"w{workers}_cores"].append(cores)
            config = GenerateConfig(
                suite=args.suite, episodes=args.episodes, explore_episodes=args.explore_episodes
            )
            env_rate, env_frames, cores = env_only_rate(config)
            rates["env"].append(env_rate)
            rates["env_cores"].append(cores)
        root = Path(tmp) / "r0-w1"
        video, data = dir_bytes(root, "videos"), dir_bytes(root, "data")
        stored_frames = json.loads((root / "meta/info.json").read_text())["total_frames"]
    ratios = [w / e for w, e in zip(rates["w1"], rates["env"], strict=True)]
    scaling = [w2 / w1 for w1, w2 in zip(rates["w1"], rates["w2"], strict=True)]
    med = {k: statistics.median(v) for k, v in rates.items()}
    print(
        json.dumps(
            {
                "suite": args.suite,
                "episodes": {
                    "oracle": args.episodes,
                    "noisy-oracle": args.explore_episodes,
                    "random": args.explore_episodes,
                },
                "steps": frames,
                "repeats": args.repeats,
                "generate_steps_per_s_1_worker": med["w1"],
                "env_only_steps_per_s": med["env"],
                "ratio_generate_to_env_only": statistics.median(ratios),
                "ratio_per_repeat": ratios,
                "generate_steps_per_s_2_workers": med["w2"],
                "scaling_1_to_2_workers": statistics.median(scaling),
                "scaling_per_repeat": scaling,
                "env_only_cores_busy": med["env_cores"],
                "generate_cores_busy_1_worker": med["w1_cores"],
                "generate_cores_busy_2_workers": med["w2_cores"],
                "video_bytes_per_1000_frames": 1000 * video / stored_frames,
                "data_bytes_per_1000_frames": 1000 * data / stored_frames,
                "env_only_steps": env_frames,
                "targets": {"ratio_generate_to_env_only": 0.85, "scaling_1_to_2_workers": 1.6},
                "cpu_count": os.cpu_count(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
