"""Reading a suite dataset into tensors: `ccfit.data.load_episodes` (each video decoded once,
sequentially) versus iterating `LeRobotDataset.__getitem__` over the same frames. Prints JSON.
Target: at least 20x.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from ccdata.record import GenerateConfig, generate  # noqa: E402
from ccfit.data import load_episodes  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--root", help="an existing dataset (default: generate a small one)")
    parser.add_argument("--suite", default="Reach")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--explore-episodes", type=int, default=1)
    parser.add_argument("--max-items", type=int, default=1500,
                        help="frames read through __getitem__ (it is slow)")  # fmt: skip
    args = parser.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.root) if args.root else Path(tmp) / "ds"
        if not args.root:
            generate(GenerateConfig(suite=args.suite, episodes=args.episodes,
                                    explore_episodes=args.explore_episodes, root=root),
                     progress=False)  # fmt: skip
        start = time.perf_counter()
        episodes = load_episodes(root)
        ours_s = time.perf_counter() - start
        frames = sum(len(e["action"]) for e in episodes)

        ds = LeRobotDataset("ccdata/bench", root=root, video_backend="pyav")
        n = min(args.max_items, len(ds))
        start = time.perf_counter()
        for i in range(n):
            ds[i]
        theirs_s = time.perf_counter() - start
    ours, theirs = frames / ours_s, n / theirs_s
    print(
        json.dumps(
            {
                "frames": frames,
                "loader_frames_per_s": ours,
                "lerobot_getitem_frames_per_s": theirs,
                "getitem_frames_timed": n,
                "speedup": ours / theirs,
                "target_speedup": 20,
                "cpu_count": os.cpu_count(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
