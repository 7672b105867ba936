"""Training the autoencoder: resumable, atomic, seeded; writes the encoder and its sidecar."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from importlib import metadata as importlib_metadata
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ccdata.errors import InputError
from ccfit.io import atomic_torch_save, rng_state, set_rng_state
from ccfit.models.encoders import (
    random_shift,
    read_encoder_sidecar,
    save_encoder,
    sidecar_path,
)
from ccfit.pretrain.config import (
    _SAMPLE_TAG,
    CHECKPOINT_VERSION,
    KIND,
    OBJECTIVE,
    PretrainConfig,
)
from ccfit.pretrain.contrastive import episode_contrast, other_frames
from ccfit.pretrain.data import (
    BatchSampler,
    FrameStore,
    check_datasets,
    load_frames,
    split_episodes,
)
from ccfit.pretrain.foreground import Foreground, weighted_image_loss
from ccfit.pretrain.model import Autoencoder, evaluate_reconstruction
from ccfit.settings import resolve_execution, torch_threads

# ============================================================================== training


def _paths(out: Path) -> tuple[Path, Path, Path]:
    """(weights, sidecar, checkpoint) for an output weights path."""
    return out, sidecar_path(out), out.with_suffix(".ckpt.pt")


def _versions() -> dict:
    out = {}
    for dist in ("ccbench", "torch", "numpy", "lerobot", "safetensors", "mujoco", "metaworld"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _finished(config: PretrainConfig, out: Path) -> dict | None:
    """The finished run's record at `out` if it was made with these settings; InputError if
    `out` holds an encoder made with other settings."""
    weights, side, ckpt = _paths(out)
    if weights.exists() and not side.is_file() and not ckpt.is_file():
        # Ours always has a sidecar, or a checkpoint while the sidecar is being written.
        raise InputError(f"{weights} exists and is not a pretraining output; choose another --out")
    if not (weights.is_file() and side.is_file()):
        return None
    try:
        record = read_encoder_sidecar(weights)
    except ValueError as err:  # the user's --out holds a broken sidecar
        raise InputError(f"{err}; choose another --out or delete it") from None
    if record.get("kind") != KIND or record.get("identity") != json.loads(
        json.dumps(config.identity())
    ):
        raise InputError(
            f"{weights} already holds an encoder pretrained with other settings; choose "
            "another --out or delete it (and its .json sidecar)"
        )
    return record


def pretrain_encoder(
    config: PretrainConfig,
    out: str | Path,
    progress: bool = True,
    on_step: Callable[[int, float], None] | None = None,
) -> dict:
    """Pretrain the encoder of `config` and write it to `out` (a `.safetensors` path).

    Resumes from `out`'s checkpoint when one exists; returns the stored metrics without
    training when `out` already holds this run's result. `on_step(step, loss)` is called after
    every gradient step; a KeyboardInterrupt (Ctrl-C, or raised by it) writes a checkpoint
    first, so rerunning continues where it stopped. Returns the metrics: per camera MSE / PSNR
    on the held-out episodes (before and after training), the same on a sample of training
    frames, first and last loss, steps, seconds.
    """
    out = Path(out)
    if out.suffix != ".safetensors":
        raise InputError(f"--out must end in .safetensors, got {out}")
    done = _finished(config, out)
    if done is not None:
        return done["metrics"]
    check_datasets(config)
    execution = resolve_execution(config)
    with torch_threads(execution.torch_threads):
        return _pretrain(config, out, execution.device, progress, on_step)


def batch_loss(model: Autoencoder, config: PretrainConfig, store: FrameStore, pairs: np.ndarray,
               rng: np.random.Generator, foreground: Foreground,
               proprio_norm: tuple[torch.Tensor, torch.Tensor],
               device: torch.device) -> torch.Tensor:  # fmt: skip
    """The objective (`OBJECTIVE`) on the frames `pairs`: their reconstruction, weighted toward
    the foreground where `foreground_weight` says, the proprio's, and, given
    `contrastive_coef`, the episode-contrastive term against another frame of each one's
    episode (`ccfit.pretrain.contrastive`). Draws from `rng` only for that other frame."""
    pix, prop = _frames(store, pairs, device)
    mask = foreground.mask(pix, pairs) if config.foreground_weight > 0 else None
    if config.augment_shift > 0 and mask is not None:  # the mask moves with its frame
        shifted = random_shift(torch.cat([pix, mask], 1), config.augment_shift)
        pix, mask = shifted[:, : pix.shape[1]], shifted[:, pix.shape[1] :]
    elif config.augment_shift > 0:
        pix = random_shift(pix, config.augment_shift)
    z = model.encode(pix, prop)
    rec, rec_prop = model.decoder(z)
    if mask is None:
        img_loss = F.mse_loss(rec, pix.float() / 255.0)
    else:
        img_loss = weighted_image_loss(rec, pix.float() / 255.0, mask, config.foreground_weight)
    mean, std = proprio_norm
    loss = img_loss + config.proprio_coef * F.mse_loss(rec_prop, (prop - mean) / std)
    if config.contrastive_coef > 0:
        other = other_frames(store.lengths(), pairs, rng)
        pix2, prop2 = _frames(store, other, device)
        if config.augment_shift > 0:
            pix2 = random_shift(pix2, config.augment_shift)
        episodes = torch.as_tensor(pairs[:, 0], device=device)
        contrast = episode_contrast(model.head(z), model.head(model.encode(pix2, prop2)),
                                    episodes, config.contrastive_temperature)  # fmt: skip
        loss = loss + config.contrastive_coef * contrast
    return loss


def _frames(store: FrameStore, pairs: np.ndarray,
            device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    pix, prop = store.batch(pairs)
    return torch.from_numpy(pix).to(device), torch.from_numpy(prop).to(device)


def _pretrain(config: PretrainConfig, out: Path, device: torch.device, progress: bool,
              on_step: Callable | None) -> dict:  # fmt: skip
    from tqdm.auto import tqdm

    weights, _, ckpt_path = _paths(out)
    identity = json.loads(json.dumps(config.identity()))
    enc_cfg = config.encoder_config()

    store, suites_manifest = load_frames(config, progress=progress)
    train_eps, held_eps = split_episodes(store.episodes, config.holdout, config.seed)
    train_pairs, held_pairs = store.index(train_eps), store.index(held_eps)
    if len(train_pairs) == 0:
        raise ValueError("no training frames: every episode was held out")
    if progress:
        gb = sum(p.nbytes for p in store.pixels) / 1e9
        print(
            f"{len(store.episodes)} episodes ({len(held_eps)} held out), "
            f"{len(train_pairs)} training and {len(held_pairs)} held-out frames ({gb:.2f} GB)"
        )
    all_prop = np.concatenate([store.proprio[e] for e in train_eps])
    mean = torch.from_numpy(all_prop.mean(0)).to(device)
    std = torch.from_numpy(all_prop.std(0)).clamp_min(1e-3).to(device)
    rng = np.random.default_rng([config.seed, _SAMPLE_TAG])
    # A fixed sample of training frames, to compare with the held-out error (overfitting).
    train_probe = train_pairs[
        np.sort(np.random.default_rng([config.seed, _SAMPLE_TAG, 1]).permutation(
            len(train_pairs))[: max(len(held_pairs), config.eval_batch_size)])
    ]  # fmt: skip

    foreground = Foreground(store.pixels, store.episodes, train_eps, config.seed,
                            config.foreground_threshold, device)  # fmt: skip
    torch.manual_seed(config.seed)
    model = Autoencoder(enc_cfg, config.decoder_channels,
                        head=config.contrastive_coef > 0).to(device)  # fmt: skip
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    step, history, window, initial = 0, [], [], None
    if ckpt_path.is_file():
        # Our own file; it holds the RNG states of ccfit.io.rng_state (NumPy and Python objects).
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if ck.get("version") != CHECKPOINT_VERSION or ck.get("identity") != identity:
            raise InputError(
                f"{ckpt_path} is a checkpoint of other settings; rerun with those or delete it"
            )
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        set_rng_state(ck["rng"], sample=rng)
        step, history, initial = int(ck["step"]), ck["history"], ck["initial_heldout"]
        window = list(ck["window"])  # losses since the last history point
    else:
        initial = evaluate_reconstruction(
            model, store, held_pairs, (mean, std), config.eval_batch_size, device, foreground
        )

    def save_checkpoint() -> None:
        atomic_torch_save({
            "version": CHECKPOINT_VERSION, "identity": identity, "step": step,
            "model": model.state_dict(), "optimizer": opt.state_dict(),
            "rng": rng_state(sample=rng), "history": history, "window": window,
            "initial_heldout": initial,
        }, ckpt_path)  # fmt: skip

    sample = BatchSampler(store, train_pairs, config.batch_from)
    start = time.perf_counter()
    bar = tqdm(total=config.steps, initial=step, desc="pretrain-encoder", unit="step",
               disable=not progress)  # fmt: skip
    try:
        while step < config.steps:
            pairs = sample(config.batch_size, rng)
            loss = batch_loss(model, config, store, pairs, rng, foreground, (mean, std), device)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip_norm)
            opt.step()
            step += 1
            value = float(loss.item())
            window.append(value)
            if step % config.log_interval == 0 or step == config.steps:
                history.append([step, float(np.mean(window))])
                bar.set_postfix(loss=f"{history[-1][1]:.4f}")
                window = []
            bar.update(1)
            if step % config.checkpoint_interval == 0 and step < config.steps:
                save_checkpoint()
            if on_step is not None:
                on_step(step, value)
    except KeyboardInterrupt:
        save_checkpoint()
        raise
    finally:
        bar.close()
    seconds = time.perf_counter() - start

    heldout = evaluate_reconstruction(
        model, store, held_pairs, (mean, std), config.eval_batch_size, device, foreground
    )
    train_eval = evaluate_reconstruction(
        model, store, train_probe, (mean, std), config.eval_batch_size, device, foreground
    )
    metrics = {
        "steps": step,
        "loss_first": history[0][1] if history else None,
        "loss_last": history[-1][1] if history else None,
        "heldout": heldout,
        "heldout_initial": initial,
        "train_sample": train_eval,
        "seconds_this_session": seconds,
    }
    if heldout is None:
        metrics["note"] = "no held-out episodes (fewer than two episodes in total)"
    frames = {"train": int(len(train_pairs)), "heldout": int(len(held_pairs))}
    record = {
        "kind": KIND,
        "identity": identity,
        "config": config.to_dict(),
        "objective": OBJECTIVE,
        "seed": config.seed,
        "versions": _versions(),
        "proprio_norm": {"mean": mean.cpu().tolist(), "std": std.cpu().tolist()},
        "data": {
            "suites": suites_manifest,
            "episodes": len(store.episodes),
            "train_episodes": len(train_eps),
            "frames": frames,
            "held_out": [store.episodes[i] for i in held_eps],
            "train": [store.episodes[i] for i in train_eps],
        },
        "metrics": metrics,
        "history": history,
    }
    save_encoder(model.encoder, enc_cfg, weights, metadata=record)
    ckpt_path.unlink(missing_ok=True)
    return metrics
