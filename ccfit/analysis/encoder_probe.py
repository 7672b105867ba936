"""Does a frozen encoder see what a task is about? Linear probes of its latent.

A frozen pretrained encoder (`ccfit pretrain-encoder`) is all a frozen-encoder run sees of the
scene: what its latent leaves out, no world model can learn. For each task, `probe_encoder`
renders `frames` frames, each from a fresh layout (`env.reset(seed=i)`) with the hand moved
along a random walk of up to `walk` uniform actions (so hand and goal are not correlated),
encodes them, and fits ridge regressions from the latent to the positions the task's state
vector holds (hand, objects, goal) on the first 80% of the frames, scoring held-out R^2 on the
rest. The same probe from the frames themselves, average-pooled to a quarter of their side,
says whether the quantity is visible at all: a quantity the pixels give and the latent does
not is one the encoder dropped. A third column scores each position from the true coordinates
of the task's other positions (`others_r2`): a latent that sees a goal floating over a cube
gives the cube as well, without seeing it.

Tasks that are one MDP from state (a suite's `same_from_state` group: BinPnP's four bin
colours, PnPBlock's two blocks) differ only in what the frames show, so for each such group
with two or more tasks probed a linear classifier tells from the same frames which task a frame
comes from: a frozen-encoder run sees those tasks differ only through its latent.

A frame takes 0.06 s (reach-xy) to 0.17 s (pnp-cube) to collect, 0.11 s on average over the
18 tasks of the six suites, measured on a 2-core CPU that ran other jobs (load ~6); there
`--suites all` took 4.5 minutes end to end at 100 frames a task, and takes about 35 at the
default 1000. Tasks are independent (each its own layouts and walks), so `workers` processes
collect them side by side with the same result.

    ccfit probe-encoder ../runs/encoders/encoder-cpu-s0.safetensors --suites all \\
        --frames 1000 --out ../runs/probe
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from ccdata.errors import InputError
from ccdata.suites import SUITES
from ccdata.tasks import get_task
from ccfit.io import atomic_write_json, atomic_write_text
from ccfit.run_files import PROBED_ENCODER

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
MIN_SPREAD = 1e-3
"""Metres: `others_r2` reads only the coordinates whose spread over the fitted frames is at
least this."""


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


def walked_layouts(task_id: str, frames: int, walk: int, seed: int, image_size: int = 64):
    """`frames` times, the environment of `task_id` and its observation after a fresh layout
    (`env.reset(seed=seed * frames + i)`) and a random walk of up to `walk` uniform actions:
    the probe's frames, the same whether they are rendered or only their states are read."""
    from ccdata.env import TaskEnv

    rng = np.random.default_rng(seed)
    env = TaskEnv(task_id, image_size=image_size, render=False, render_mode="rgb_array")
    try:
        for i in range(frames):
            obs, _ = env.reset(seed=seed * frames + i)
            for _ in range(int(rng.integers(0, walk + 1))):
                obs, _, terminated, truncated, _ = env.step(
                    rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
                )
                if terminated or truncated:
                    break
            yield env, obs
    finally:
        env.close()


def collect(encoder, task_id: str, frames: int, image_size: int, walk: int,
            seed: int) -> dict[str, np.ndarray]:  # fmt: skip
    """(latent, pooled pixels, state) of `frames` frames of `task_id`, as the module says.

    Only the frame the walk ends on is rendered (`TaskEnv.render`: the images a rendering
    env's observation holds, identical arrays): rendering all of the walk's ~15 steps made a
    frame 2 to 6 times slower (0.4 s a frame on a busy 2-core CPU)."""
    from ccfit.obs import obs_to_arrays

    latents, pixels, states = [], [], []
    for env, obs in walked_layouts(task_id, frames, walk, seed, image_size):
        arrays = obs_to_arrays(camera_views(env) | obs, "pixels")
        with torch.no_grad():
            z = encoder({k: torch.as_tensor(v)[None] for k, v in arrays.items()})
            px = torch.as_tensor(arrays["pixels"])[None].float() / 255.0
            pooled = torch.nn.functional.avg_pool2d(px, POOL)
        latents.append(z[0].float().numpy())
        pixels.append(pooled.flatten().numpy())
        states.append(np.asarray(obs["state"], dtype=np.float64))
    return {"latent": np.stack(latents), "pixels": np.stack(pixels), "state": np.stack(states)}


def collect_states(task_id: str, frames: int, walk: int, seed: int) -> np.ndarray:
    """The states of the frames `collect` renders with the same arguments, without rendering
    (pick-cube: 0.05 s a frame beside two other jobs, against 0.06-0.17 s rendered): what
    `others_r2` reads."""
    return np.stack([np.asarray(obs["state"], dtype=np.float64)
                     for _, obs in walked_layouts(task_id, frames, walk, seed)])  # fmt: skip


def camera_views(env) -> dict[str, np.ndarray]:
    """The images of `env`'s current frame keyed by camera, as a rendering env observes them
    (`TaskEnv.render` gives them side by side in `CAMERAS` order)."""
    from ccdata.render import CAMERAS

    views = np.split(env.render(), len(CAMERAS), axis=1)
    return dict(zip(CAMERAS, views, strict=True))


def others_r2(state: np.ndarray, name: str) -> list[float | None]:
    """Held-out R^2 per coordinate of position `name` from the true coordinates of the task's
    other positions (`state`): what a latent that held only those would score. Where a task
    ties two positions (pick-cube's goal floats over its cube; place-cube's cube is in the
    hand), a latent's score at or below this is no evidence that it sees the position itself."""
    others = np.concatenate([state[:, dims] for other, dims in POSITIONS.items()
                             if other != name], axis=1)  # fmt: skip
    # A coordinate that hardly varies in the fit (a drawer the walk nudged in a few frames)
    # would be scaled up to unit spread and swing the held-out predictions: it is left out.
    varies = others[: int(TRAIN_FRACTION * len(others))].std(0) >= MIN_SPREAD
    return ridge_r2(others[:, varies], state[:, POSITIONS[name]])


def probe_rows(task_id: str, data: dict[str, np.ndarray]) -> list[dict]:
    """One row per position the task's frames vary in: R^2 per coordinate from the latent,
    from the pooled pixels, and from the task's other positions (`others_r2`)."""
    rows = []
    for name, dims in POSITIONS.items():
        target = data["state"][:, dims]
        latent = ridge_r2(data["latent"], target)
        pixels = ridge_r2(data["pixels"], target, RIDGE * 10)  # more inputs than frames
        others = others_r2(data["state"], name)
        keep = [j for j, r in enumerate(latent) if r is not None]
        if keep:
            rows.append({"task": task_id, "position": name,
                         "axes": "".join(AXES[j] for j in keep),
                         "latent_r2": [latent[j] for j in keep],
                         "pixels_r2": [pixels[j] for j in keep],
                         "others_r2": [others[j] for j in keep]})  # fmt: skip
    return rows


def select_tasks(suites: str | None, tasks: str | None) -> tuple[list[str], list[str]]:
    """(suites asked, tasks to probe) from comma lists as the command line gives them: every
    task of the suites (`all`: every suite) in suite order, then the tasks named, each once.
    InputError for an unknown name or a selection that names nothing."""
    suite_names = [n.strip() for n in (suites or "").split(",") if n.strip()]
    if [n.lower() for n in suite_names] == ["all"]:
        suite_names = list(SUITES)
    for name in suite_names:
        if name not in SUITES:
            raise InputError(f"unknown suite {name!r}; valid suites: {', '.join(SUITES)} or 'all'")
    named = [get_task(t.strip()).id for t in (tasks or "").split(",") if t.strip()]
    task_ids = [t for name in suite_names for t in SUITES[name].task_ids] + named
    if not task_ids:
        raise InputError("give --suites or --tasks (or both): they name no task")
    return list(dict.fromkeys(suite_names)), list(dict.fromkeys(task_ids))


def identity_groups(task_ids: list[str]) -> list[tuple[str, list[str]]]:
    """(suite, probed tasks) of each suite's `same_from_state` group of which two or more
    tasks are among `task_ids`; a group two suites share counts once."""
    groups, seen = [], set()
    for suite in SUITES.values():
        for group in suite.same_from_state:
            probed = [t for t in group if t in task_ids]
            if len(probed) >= 2 and tuple(probed) not in seen:
                seen.add(tuple(probed))
                groups.append((suite.name, probed))
    return groups


def ridge_accuracy(per_class: list[np.ndarray], ridge: float = RIDGE) -> float:
    """Held-out accuracy of a linear classifier telling apart the classes whose rows (frames)
    are `per_class`: a ridge regression onto one-hot labels, argmax, fitted on the first
    `TRAIN_FRACTION` of each class's rows (inputs standardised on those) and scored on the
    rest. Splitting each class apart keeps every class in both splits; the closed-form fit does
    not depend on the rows' order."""
    cuts = [int(TRAIN_FRACTION * len(x)) for x in per_class]
    train = np.concatenate([x[:k] for x, k in zip(per_class, cuts, strict=True)])
    held = np.concatenate([x[k:] for x, k in zip(per_class, cuts, strict=True)])
    labels = np.concatenate([np.full(k, c) for c, k in enumerate(cuts)])
    held_labels = np.concatenate([np.full(len(x) - k, c) for c, (x, k)
                                  in enumerate(zip(per_class, cuts, strict=True))])  # fmt: skip
    mu, sd = train.mean(0), train.std(0) + 1e-6
    a, b = (train - mu) / sd, (held - mu) / sd
    onehot = np.eye(len(per_class))[labels]
    share = onehot.mean(0)  # the intercept: each class's share of the training rows
    w = np.linalg.solve(a.T @ a + ridge * np.eye(a.shape[1]), a.T @ (onehot - share))
    return float(((b @ w + share).argmax(1) == held_labels).mean())


def classification_rows(task_ids: list[str], data: dict[str, dict[str, np.ndarray]]) -> list[dict]:
    """One row per `identity_groups` group: held-out accuracy of telling its tasks apart from
    the latent and from the pooled pixels of their frames (`data[task]`), and chance."""
    rows = []
    for suite, group in identity_groups(task_ids):
        latent = ridge_accuracy([data[t]["latent"] for t in group])
        pixels = ridge_accuracy([data[t]["pixels"] for t in group], RIDGE * 10)  # as probe_rows
        rows.append({"suite": suite, "tasks": group,
                     "frames": min(len(data[t]["latent"]) for t in group),
                     "latent_accuracy": latent, "pixels_accuracy": pixels,
                     "chance": 1.0 / len(group)})  # fmt: skip
    return rows


def _collect_in_worker(path: str, task_id: str, frames: int, walk: int, seed: int,
                      threads: int) -> dict[str, np.ndarray]:  # fmt: skip
    """`collect` in a worker process: the encoder loaded there, on the caller's thread count
    (so that its latents are the ones a single process computes)."""
    from ccfit.models.encoders import load_frozen_encoder
    from ccfit.settings import torch_threads

    encoder, spec = load_frozen_encoder(path)
    with torch_threads(threads):
        return collect(encoder, task_id, frames, int(spec["image_size"]), walk, seed)


def _collected(path: str | Path, encoder, image_size: int, task_ids: list[str], frames: int,
               walk: int, seed: int, workers: int) -> Iterator[dict[str, np.ndarray]]:  # fmt: skip
    """`collect` of each task in `task_ids` order, by `workers` processes at once."""
    if workers <= 1 or len(task_ids) <= 1:
        for task_id in task_ids:
            yield collect(encoder, task_id, frames, image_size, walk, seed)
        return
    # Spawned, not forked: each worker gets its own simulator and GL context.
    pool = ProcessPoolExecutor(min(workers, len(task_ids)), mp_context=get_context("spawn"))
    try:
        futures = [pool.submit(_collect_in_worker, str(path), task_id, frames, walk, seed,
                               torch.get_num_threads()) for task_id in task_ids]  # fmt: skip
        for future in futures:
            yield future.result()
    finally:
        pool.shutdown(cancel_futures=True)


def probe_encoder(path: str | Path, task_ids: list[str], frames: int = 1000, walk: int = 30,
                  seed: int = 0, suites: Sequence[str] = (), workers: int = 1) -> dict:  # fmt: skip
    """Probe the frozen encoder at `path` on each task (module docstring); `suites`: the
    suites asked for, recorded; `workers`: processes collecting frames (no effect on the
    result)."""
    from ccfit.models.encoders import load_frozen_encoder, weights_sha256

    try:
        encoder, spec = load_frozen_encoder(path)
    except ValueError as err:  # missing, foreign or mismatched file: the user's to fix
        raise InputError(str(err)) from None
    to_classify = {t for _, group in identity_groups(task_ids) for t in group}
    rows, kept = [], {}
    collected = _collected(path, encoder, int(spec["image_size"]), task_ids, frames, walk, seed,
                           workers)  # fmt: skip
    for task_id, data in zip(task_ids, collected, strict=True):
        rows += probe_rows(task_id, data)
        if task_id in to_classify:  # only these frames are needed again
            kept[task_id] = data
    # The weights by name and content, not by where they lay on the machine that probed them.
    weights = Path(path)
    return {"encoder": weights.name,
            "encoder_sha256": weights_sha256(weights),
            "suites": list(suites), "tasks": list(task_ids),
            "frames": frames, "walk": walk,
            "seed": seed, "ridge": RIDGE, "train_fraction": TRAIN_FRACTION, "pool": POOL,
            "rows": rows, "classification": classification_rows(task_ids, kept)}  # fmt: skip


def markdown(result: dict) -> str:
    """The probe's tables: R^2 per coordinate, latent against pixels and against the task's
    other positions (`others_r2`); then, where the probe
    classified (an older probe.json has no `classification`), the accuracy of telling a
    group's tasks apart."""

    def fmt(values: list[float]) -> str:
        return ", ".join(f"{v:.2f}" for v in values)

    # An older probe.json has no `others_r2`: its table has no such column.
    others = all("others_r2" in r for r in result["rows"])
    lines = ["| task | position | axes | from the latent | from the pixels |"
             + (" from the other positions |" if others else ""),
             "|---|---|---|---|---|" + ("---|" if others else "")]  # fmt: skip
    lines += [f"| {r['task']} | {r['position']} | {r['axes']} | {fmt(r['latent_r2'])} | "
              f"{fmt(r['pixels_r2'])} |" + (f" {fmt(r['others_r2'])} |" if others else "")
              for r in result["rows"]]  # fmt: skip
    classification = result.get("classification") or []
    if classification:
        lines += ["", "| suite | which task of | frames per task | from the latent | "
                  "from the pixels | chance |", "|---|---|---|---|---|---|"]  # fmt: skip
        lines += [f"| {c['suite']} | {', '.join(c['tasks'])} | {c['frames']} | "
                  f"{c['latent_accuracy']:.2f} | {c['pixels_accuracy']:.2f} | {c['chance']:.2f} |"
                  for c in classification]  # fmt: skip
    return "\n".join(lines) + "\n"


def probed_sidecar(encoder: str | Path) -> dict | None:
    """The sidecar of the weights file `encoder` (how it was pretrained) as its probe folder
    keeps it, the weights named as probed (a file renamed since pretraining keeps its first
    name in its own sidecar); None for a file without one (the older single-file format)."""
    from ccfit.models.encoders import read_encoder_sidecar, sidecar_path

    if not sidecar_path(encoder).is_file():
        return None
    try:
        record = read_encoder_sidecar(encoder)
    except ValueError as err:  # a damaged sidecar: the user's to fix, before the probe runs
        raise InputError(str(err)) from None
    return {**record, "weights": Path(encoder).name}


def write_probe(result: dict, out: Path, sidecar: dict | None = None) -> list[Path]:
    """probe.json and probe.md in `out`, and the probed encoder's `sidecar` (`probed_sidecar`)
    as encoder.json, its paths as published (`ccfit.portable`): a folder `results/probe/`
    takes as it is."""
    from ccfit.portable import portable

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "probe.json", result)
    atomic_write_text(out / "probe.md", markdown(result))
    written = [out / "probe.json", out / "probe.md"]
    if sidecar is not None:
        text = json.dumps(portable(sidecar), indent=2, sort_keys=True) + "\n"
        atomic_write_text(out / PROBED_ENCODER, text)
        written.append(out / PROBED_ENCODER)
    return written
