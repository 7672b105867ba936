"""Does a frozen encoder see what a task is about? Linear probes of its latent.

A frozen pretrained encoder (`ccfit pretrain-encoder`) is all a frozen-encoder run sees of the
scene: what its latent leaves out, no world model can learn. For each task, `probe_encoder`
renders `frames` frames, each from a fresh layout (`env.reset(seed=i)`) with the hand moved
along a random walk of up to `walk` uniform actions (so hand and goal are not correlated),
encodes them, and fits ridge regressions from the latent to the positions the task's state
vector holds (hand, objects, goal) on the first 80% of the frames, scoring held-out R^2 on the
rest. The same probe from the frames themselves, average-pooled to a quarter of their side,
says whether the quantity is visible at all: a quantity the pixels give and the latent does
not is one the encoder dropped.

    ccfit probe-encoder ../runs/encoders/encoder-cpu-s0.safetensors --tasks reach-xy \\
        --frames 1500 --out ../runs/probe
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ccfit.io import atomic_write_json, atomic_write_text

POSITIONS = {"hand": slice(0, 3), "object": slice(4, 7), "object 2": slice(11, 14),
             "goal": slice(36, 39)}  # fmt: skip
"""Where Meta-World's 39-D state vector keeps each position (x, y, z); absent objects are
zeros there, and a coordinate that never varies is left out of the scores."""
RIDGE = 10.0
"""Ridge penalty on standardised inputs (1, 10 and 100 gave the same verdicts on reach-xy)."""
TRAIN_FRACTION = 0.8
POOL = 4
"""The pixel probe's frames are average-pooled by this factor (64 px -> 16 px)."""
AXES = "xyz"


def ridge_r2(x: np.ndarray, y: np.ndarray, ridge: float = RIDGE) -> list[float | None]:
    """Held-out R^2 per column of `y` of a ridge regression from `x` fitted on the first
    `TRAIN_FRACTION` of the rows (inputs standardised on those); None for a column that does
    not vary in the held-out rows."""
    k = int(TRAIN_FRACTION * len(x))
    mu, sd = x[:k].mean(0), x[:k].std(0) + 1e-6
    a = (x - mu) / sd
    my = y[:k].mean(0)
    w = np.linalg.solve(a[:k].T @ a[:k] + ridge * np.eye(a.shape[1]), a[:k].T @ (y[:k] - my))
    pred, held = a[k:] @ w + my, y[k:]
    var = held.var(0)
    return [float(1.0 - ((pred[:, j] - held[:, j]) ** 2).mean() / var[j]) if var[j] > 1e-8
            else None for j in range(y.shape[1])]  # fmt: skip


def collect(encoder, task_id: str, frames: int, image_size: int, walk: int,
            seed: int) -> dict[str, np.ndarray]:  # fmt: skip
    """(latent, pooled pixels, state) of `frames` frames of `task_id`, as the module says."""
    from ccdata import make_env
    from ccfit.obs import obs_to_arrays

    rng = np.random.default_rng(seed)
    env = make_env(task_id, render=True, image_size=image_size)
    latents, pixels, states = [], [], []
    try:
        for i in range(frames):
            obs, _ = env.reset(seed=seed * frames + i)
            for _ in range(int(rng.integers(0, walk + 1))):
                obs, _, terminated, truncated, _ = env.step(
                    rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
                )
                if terminated or truncated:
                    break
            arrays = obs_to_arrays(obs, "pixels")
            with torch.no_grad():
                z = encoder({k: torch.as_tensor(v)[None] for k, v in arrays.items()})
                px = torch.as_tensor(arrays["pixels"])[None].float() / 255.0
                pooled = torch.nn.functional.avg_pool2d(px, POOL)
            latents.append(z[0].float().numpy())
            pixels.append(pooled.flatten().numpy())
            states.append(np.asarray(obs["state"], dtype=np.float64))
    finally:
        env.close()
    return {"latent": np.stack(latents), "pixels": np.stack(pixels), "state": np.stack(states)}


def probe_rows(task_id: str, data: dict[str, np.ndarray]) -> list[dict]:
    """One row per position the task's frames vary in: R^2 per coordinate from the latent and
    from the pooled pixels."""
    rows = []
    for name, dims in POSITIONS.items():
        target = data["state"][:, dims]
        latent = ridge_r2(data["latent"], target)
        pixels = ridge_r2(data["pixels"], target, RIDGE * 10)  # more inputs than frames
        keep = [j for j, r in enumerate(latent) if r is not None]
        if keep:
            rows.append({"task": task_id, "position": name,
                         "axes": "".join(AXES[j] for j in keep),
                         "latent_r2": [latent[j] for j in keep],
                         "pixels_r2": [pixels[j] for j in keep]})  # fmt: skip
    return rows


def probe_encoder(path: str | Path, task_ids: list[str], frames: int = 1000, walk: int = 30,
                  seed: int = 0) -> dict:  # fmt: skip
    """Probe the frozen encoder at `path` on each task (module docstring)."""
    from ccdata.errors import InputError
    from ccfit.models.encoders import load_frozen_encoder, weights_sha256

    try:
        encoder, spec = load_frozen_encoder(path)
    except ValueError as err:  # missing, foreign or mismatched file: the user's to fix
        raise InputError(str(err)) from None
    rows = []
    for task_id in task_ids:
        data = collect(encoder, task_id, frames, int(spec["image_size"]), walk, seed)
        rows += probe_rows(task_id, data)
    # The weights by name and content, not by where they lay on the machine that probed them.
    weights = Path(path)
    return {"encoder": weights.name,
            "encoder_sha256": weights_sha256(weights),
            "frames": frames, "walk": walk,
            "seed": seed, "ridge": RIDGE, "train_fraction": TRAIN_FRACTION, "pool": POOL,
            "rows": rows}  # fmt: skip


def markdown(result: dict) -> str:
    """The probe's table: R^2 per coordinate, latent against pixels."""

    def fmt(values: list[float]) -> str:
        return ", ".join(f"{v:.2f}" for v in values)

    lines = ["| task | position | axes | from the latent | from the pixels |",
             "|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['task']} | {r['position']} | {r['axes']} | {fmt(r['latent_r2'])} | "
              f"{fmt(r['pixels_r2'])} |" for r in result["rows"]]  # fmt: skip
    return "\n".join(lines) + "\n"


def write_probe(result: dict, out: Path) -> tuple[Path, Path]:
    """probe.json and probe.md in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "probe.json", result)
    atomic_write_text(out / "probe.md", markdown(result))
    return out / "probe.json", out / "probe.md"
