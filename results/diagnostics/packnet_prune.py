"""Does PackNet's prune ruin a learnt grasp, and how much retraining brings it back?

    python results/diagnostics/packnet_prune.py RUNS/pick-cube-tdmpc2-s0-demo0.25 \
        > results/diagnostics/packnet_prune.jsonl

From a finished single-task TD-MPC2 run (`ccfit train`: final weights, heads and replay), as
PackNet treats a curriculum's first task: evaluate (10 layouts x 3 noise seeds, normalised),
prune (`after_task`: keep a quarter of the weights by magnitude), then retrain with ordinary
updates on the task's replay (only the kept weights move), evaluating after 0, 1000, 3000 and
6000 retraining updates. One JSON line per evaluation point.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from ccdata.errors import OneLineParser, run_script
from ccfit.continual.base import TaskData, make_method
from ccfit.continual.packnet import PackNetConfig
from ccfit.io import seed_everything
from ccfit.replay_store import load_rows
from ccfit.train import load_task_run
from ccfit.train.evaluate import Evaluator
from ccfit.train.run import make_replay
from ccfit.train.update import UpdateStep

RETRAINING = (0, 1000, 3000, 6000)


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="packnet_prune.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished TD-MPC2 `ccfit train` run")
    run = parser.parse_args(argv).run
    torch.set_num_threads(1)
    seed_everything(0)  # the updates' own noise (the replay samples with its seeded generator)
    loaded = load_task_run(run, "cpu")
    cfg, model, heads, state = loaded.cfg, loaded.model, loaded.heads, loaded.checkpoint
    heads.train()  # as the trainer's heads during updates (Q's dropout); acting sets eval
    replay = make_replay(cfg, model, cfg.task, 0, None)
    load_rows(replay, run, state["buffer"], state["replay_files"])
    method = make_method(PackNetConfig(retrain_steps=max(RETRAINING)), num_tasks=3, seed=0)
    method.before_task(0, model.backbone)
    update = UpdateStep(model, heads, method)
    view = lambda i: method.evaluating(i, model.backbone)  # noqa: E731
    evaluator = Evaluator(model, {0: cfg.task}, seed=0, obs_mode="state", image_size=64,
                          episodes=10, episode_steps=cfg.train.episode_steps,
                          view=view)  # fmt: skip
    evaluator.heads[0] = heads

    def report(after: str) -> None:
        records = [evaluator.evaluate([0], stage=0, global_step=noise, task_step=None)[0]
                   for noise in (1, 2, 3)]  # fmt: skip
        scores = [round(r["normalized_return"], 1) for r in records]
        success = [r["success_rate"] for r in records]
        print(json.dumps({"after": after, "normalized": scores, "success": success}), flush=True)

    report("trained (before the prune)")
    mcfg = model.cfg
    data = TaskData.from_buffer(0, replay, batch_size=mcfg.batch_size, seq_len=mcfg.seq_len,
                                backbone_loss=model.backbone_loss, device=model.device)  # fmt: skip
    method.after_task(0, model.backbone, data)
    done = 0
    for target in RETRAINING:
        while done < target:
            update(replay.sample(mcfg.batch_size, mcfg.seq_len, cfg.train.demo_fraction))
            done += 1
        report(f"prune + {done} retraining updates")


if __name__ == "__main__":
    sys.exit(run_script(main, "packnet_prune.py"))
