"""From which point of its task a single-task run's policy finishes what the oracle started.

    python results/diagnostics/handover.py RUNS/tdmpc2-stack-blocks-s0 [--at 0,1,2,3,4,5,7]

handover.jsonl beside it: `--at 0,1,2,3,4,5,6,7,8` over the single-task runs (TD-MPC2, `cpu`,
state, seed 0, Grasp's recipe) of stack-blocks (100 000 steps), stack-blocks with the
demonstrations at 0.5 (60 000), pnp-red-block (ended at 41 000) and box-pnp-close (100 000),
in that order, then the demonstration-cloning stack-blocks run, `--acting policy` lines, then
`--at 0,0.05,0.1,0.2,0.5` over DreamerV3's pick-cube run that clones the demonstrations (lines
58-67), at its checkpoint of 47 000 steps and at its end, 100 000, and last over its control
without cloning (lines 68-77), at 47 000 and at its end, 60 000 (README.md here lists each
line's command).

A policy that never completes a composition may fail at its first stage or at every stage. On
each of the run's first LAYOUTS evaluation layouts (`--layouts`, default 10) the task's
scripted oracle plays until the scene's raw reward (in [0, 10]; a composition's second stage
pays 5-10) first reaches T, and the run's policy plays the rest of the episode, acting as
evaluation does (its last weights, MPPI or the actor in eval mode, the run's observations,
warm start from nothing at the handover). T = 0 hands over at the first step: the run alone.
`--acting policy`: the run acts by its policy's mean alone instead (TD-MPC2-style models).
Per T and layout: the step of the handover (null where the oracle never reached T), success,
the best raw reward after the handover and the last. One JSON line per T.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from ccdata.env import make_env
from ccdata.errors import InputError, OneLineParser, run_script
from ccdata.policies import make_policy
from ccfit.analysis.reading import policy_alone
from ccfit.io import seeded
from ccfit.obs import model_input, obs_to_arrays
from ccfit.train import load_task_run
from ccfit.train.evaluate import eval_seeds

NOISE_SEED = 1


def handover_episode(env, oracle, model, heads, obs_mode: str, seed: int, at: float) -> dict:
    """One episode of layout `seed`: the oracle until the raw reward reaches `at`, then the
    run's policy."""
    obs, _ = env.reset(seed=seed)
    oracle.reset()
    step, handed, state, after, success = 0, None, None, [], False
    done = False
    while not done:
        if handed is None and at <= 0:
            handed = step
        if handed is None:
            action = oracle.act(obs)
        else:
            if handed == step:  # the policy's first step: an episode's start for its state
                state = model.initial_state(heads, 1)
            x = model_input([obs_to_arrays(obs, obs_mode)], model.device)
            actions, state = model.act(x, heads, state, eval_mode=True)
            action = np.asarray(actions[0], np.float32)
        obs, _, terminated, truncated, info = env.step(action)
        step += 1
        raw = float(info["raw_reward"])
        if handed is not None:
            after.append(raw)
            success = success or bool(info["success"])
        elif raw >= at:
            handed = step
        done = terminated or truncated
    if handed is None or not after:
        return {"handover_step": None, "success": None, "best_raw": None, "last_raw": None}
    return {"handover_step": handed, "success": success, "best_raw": round(max(after), 2),
            "last_raw": round(after[-1], 2)}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="handover.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished `ccfit train` run directory")
    parser.add_argument(
        "--at",
        default="0,1,2,3,4,5,7",
        help="raw rewards at which the policy takes over (default 0,1,2,3,4,5,7)",
    )
    parser.add_argument(
        "--layouts",
        type=int,
        default=10,
        help="how many of the run's evaluation layouts (default 10)",
    )
    parser.add_argument(
        "--acting",
        choices=("evaluation", "policy"),
        default="evaluation",
        help="how the run acts: as evaluation does (default), or by its policy's mean alone "
        "(TD-MPC2-style models)",
    )
    args = parser.parse_args(argv)
    try:
        thresholds = [float(t) for t in args.at.split(",")]
    except ValueError:
        raise InputError(f"--at takes comma-separated numbers, got {args.at!r}") from None
    if args.layouts < 1:
        raise InputError(f"--layouts must be >= 1, got {args.layouts}")
    torch.set_num_threads(1)
    loaded = load_task_run(args.run, "cpu")
    cfg, model = loaded.cfg, loaded.model
    env = make_env(cfg.task, render=cfg.obs == "pixels", image_size=cfg.image_size,
                   episode_steps=cfg.train.episode_steps)  # fmt: skip
    oracle = make_policy("oracle", cfg.task)
    seeds = eval_seeds(cfg.seed, 0, args.layouts)
    if args.acting == "policy" and not hasattr(model, "pi"):
        raise InputError(f"{args.run}: a {cfg.model.type} run has no policy to act alone "
                         "(--acting policy reads TD-MPC2-style models)")  # fmt: skip
    for at in thresholds:
        with seeded(NOISE_SEED, model.device), policy_alone(model, args.acting == "policy"):
            episodes = [handover_episode(env, oracle, model, loaded.heads, cfg.obs, s, at)
                        for s in seeds]  # fmt: skip
        print(json.dumps({"run": args.run.name, "task": cfg.task,
                          "task_step": loaded.checkpoint["task_step"], "handover_at_raw": at,
                          "acting": args.acting,
                          **{k: [e[k] for e in episodes] for k in episodes[0]}}),
              flush=True)  # fmt: skip


if __name__ == "__main__":
    sys.exit(run_script(main, "handover.py"))
