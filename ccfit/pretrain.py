"""Autoencoder pretraining of the frozen encoder (paper Sec. III-E, frozen-encoder diagnostic).

The encoder is exactly the pixel encoder TD-MPC2 (and PWM, which shares TD-MPC2's encoder)
builds in pixel mode: `build_encoder(tdmpc2_preset(model_preset, "pixels"))`, so the saved
weights load with `load_frozen_encoder` into a model of the same preset. A decoder of
transposed convolutions reconstructs the 9-channel image (and the 7-D proprio) from the latent.

Objective (per batch of frames):

    loss = MSE(image) + proprio_coef * MSE(proprio)

- MSE(image): mean squared error over all 9 channels and pixels, with both the target and the
  decoder's output on the [0, 1] scale (uint8 / 255). PSNR on that scale is 10 log10(1 / MSE).
- MSE(proprio): mean squared error of the standardised proprio (per-dimension mean and standard
  deviation of the training frames, stored in the sidecar); the encoder itself reads the raw
  proprio, exactly as a model does online.

Data: the oracle (expert) episodes of every task of the requested suites, read from the suites'
LeRobot datasets by `ccfit.data.load_episodes` and stacked by `ccfit.obs.obs_to_arrays`, the
function live observations go through. A task in several suites (pnp-cube) is read once, from
the first suite (in `ccdata.SUITES` order) that holds it. Episodes are split per task into
training and held-out sets (seeded); reconstruction error per camera is reported on the held-out
episodes.

Output `OUT.safetensors` (weights, settings in the header) and `OUT.json` (settings, config,
data manifest, seed, versions, metrics, loss history). While training, `OUT.ckpt.pt` holds a
resumable checkpoint (model, optimiser, RNG states, step); rerunning the same command resumes
from it, and a finished run (weights and sidecar present, same settings) is not redone.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ccdata.render import CAMERAS
from ccdata.suites import SUITES
from ccfit.config import PRESETS, TDMPC2Config, tdmpc2_preset
from ccfit.models.encoders import (
    build_encoder,
    random_shift,
    read_encoder_sidecar,
    save_encoder,
    sidecar_path,
)
from ccfit.models.layers import mlp
from ccfit.pretrain_data import FrameStore, check_datasets, load_oracle_frames, split_episodes

KIND = "ccfit-pretrained-encoder"
"""The sidecar's 'kind': an encoder made by this module."""
CHECKPOINT_VERSION = 1
_SAMPLE_TAG = 2  # seed stream of batch sampling, independent of the split's (SPLIT_TAG)
_NOT_IDENTITY = ("device", "torch_threads", "checkpoint_interval", "log_interval")
"""Config fields that may change between a run and its resumption (they do not change what is
learnt, up to floating-point differences across devices)."""

OBJECTIVE = (
    "MSE(image) + proprio_coef * MSE(proprio); image MSE over the 9 stacked channels on the "
    "[0, 1] scale (uint8 / 255); proprio MSE on the proprio standardised with the training "
    "frames' mean and std (the encoder reads the raw proprio)"
)


# ============================================================================== config


@dataclass
class PretrainConfig:
    """Autoencoder pretraining of the frozen encoder. Validated on construction.

    The encoder's sizes are not fields: they come from `tdmpc2_preset(model_preset, 'pixels',
    image_size=image_size)`, so the encoder always fits the TD-MPC2 (or PWM) preset it is meant
    for. Preset values for steps, batch size, learning rate and decoder width are this
    project's choices (the paper gives none).
    """

    model_preset: str = "cpu"
    """TD-MPC2 preset ('smoke', 'cpu', 'paper' or a size such as '19M') whose pixel encoder is
    pretrained; use the frozen encoder with a model of this preset."""
    suites: tuple[str, ...] = tuple(SUITES)
    """Suites whose oracle episodes are used (default: all six)."""
    dataset_roots: dict[str, str] = field(default_factory=dict)
    """Suite -> dataset directory; a suite not listed uses
    `ccdata.settings.suite_dataset_root(suite)` (LeRobot's cache for `ccdata/<Suite>`)."""
    image_size: int = 64
    """Camera image side; every dataset must have been generated at this size."""
    steps: int = 20_000
    """Gradient steps."""
    batch_size: int = 64
    """Frames per gradient step, sampled uniformly from the training episodes' frames."""
    lr: float = 5e-4
    """Adam learning rate (encoder and decoder)."""
    grad_clip_norm: float = 20.0
    """Gradient-norm clip (TD-MPC2's value)."""
    proprio_coef: float = 0.1
    """Weight of the standardised-proprio MSE against the [0, 1]-scale image MSE."""
    decoder_channels: int = 32
    """Channels of the decoder's last transposed convolution (earlier layers: 2x and 4x)."""
    augment_shift: int = 0
    """Random-shift augmentation in pixels, applied identically to the input and the
    reconstruction target (0: none). The encoder's own training-time shift is never used."""
    holdout: float = 0.1
    """Fraction of each task's episodes held out for evaluation (at least one episode overall
    when there are two or more)."""
    frame_stride: int = 1
    """Keep every `frame_stride`-th frame of each episode (memory: ~37 KB per 64 px frame)."""
    eval_batch_size: int = 256
    """Frames per forward pass in evaluation."""
    checkpoint_interval: int = 1_000
    """Write a resumable checkpoint every this many steps (and on Ctrl-C)."""
    log_interval: int = 100
    """Steps averaged into each point of the loss history."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu' or 'cuda'."""
    torch_threads: int = 0
    """CPU threads for torch during pretraining (0: leave torch's setting); restored after."""
    seed: int = 0
    """Seeds the initialisation, the episode split, batch sampling and augmentation."""

    def __post_init__(self) -> None:
        if isinstance(self.suites, str):  # 'all' or a comma list, as on the command line
            names = [s.strip() for s in self.suites.split(",") if s.strip()]
            self.suites = tuple(SUITES) if [n.lower() for n in names] == ["all"] else names
        self.suites = tuple(self.suites)
        bad = [s for s in self.suites if s not in SUITES]
        if bad or not self.suites:
            raise ValueError(
                f"unknown suite(s) {bad or '(none given)'}; valid: {', '.join(SUITES)} or 'all'"
            )
        if len(set(self.suites)) != len(self.suites):
            raise ValueError(f"PretrainConfig.suites lists a suite twice: {self.suites}")
        self.dataset_roots = {str(k): str(v) for k, v in dict(self.dataset_roots).items()}
        extra = [s for s in self.dataset_roots if s not in SUITES]
        if extra:
            raise ValueError(f"dataset_roots has unknown suite(s) {extra}; valid: {list(SUITES)}")
        for name in ("steps", "batch_size", "decoder_channels", "frame_stride",
                     "eval_batch_size", "checkpoint_interval", "log_interval"):  # fmt: skip
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PretrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        checks = [
            (self.lr > 0 and self.grad_clip_norm > 0, "lr and grad_clip_norm must be > 0"),
            (self.proprio_coef >= 0, "proprio_coef must be >= 0"),
            (self.augment_shift >= 0, "augment_shift must be >= 0"),
            (0.0 <= self.holdout < 1.0, "holdout must be in [0, 1)"),
            (self.device in ("auto", "cpu", "cuda"), "device must be one of auto, cpu, cuda"),
            (self.torch_threads >= 0, "torch_threads must be >= 0"),
            (self.seed >= 0, "seed must be >= 0"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"PretrainConfig: {msg}")
        self.encoder_config()  # unknown preset or bad image size -> ValueError

    def encoder_config(self) -> TDMPC2Config:
        """The TD-MPC2 pixel-mode config whose encoder this run pretrains."""
        return tdmpc2_preset(self.model_preset, "pixels", image_size=self.image_size)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> PretrainConfig:
        """`smoke`: seconds (CI); `cpu`: minutes to an hour on 2 cores; `paper`: GPU scale.
        The encoder's sizes follow the TD-MPC2 preset of the same name."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; valid: {', '.join(PRESETS)}")
        base = {
            "smoke": dict(steps=100, batch_size=16, lr=1e-3, decoder_channels=16,
                          checkpoint_interval=50, log_interval=10),
            "cpu": dict(steps=10_000, batch_size=64, lr=5e-4, decoder_channels=16,
                        augment_shift=4, checkpoint_interval=1_000, log_interval=100),
            "paper": dict(steps=100_000, batch_size=256, lr=3e-4, decoder_channels=64,
                          augment_shift=4, checkpoint_interval=5_000, log_interval=500),
        }[name]  # fmt: skip
        return cls(**{"model_preset": name, **base, **overrides})

    def resolved_roots(self) -> dict[str, Path]:
        """Suite -> dataset directory for every suite of the run."""
        from ccdata.settings import suite_dataset_root

        return {
            s: Path(self.dataset_roots[s]).expanduser().resolve()
            if s in self.dataset_roots else suite_dataset_root(s)
            for s in self.suites
        }  # fmt: skip

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["suites"] = list(self.suites)
        d["dataset_roots"] = {s: str(p) for s, p in self.resolved_roots().items()}
        return d

    def identity(self) -> dict:
        """The settings a checkpoint or finished output must share to be resumed or reused."""
        return {k: v for k, v in self.to_dict().items() if k not in _NOT_IDENTITY}


# =============================================================================== model


class PixelDecoder(nn.Module):
    """Latent -> (9-channel image on the [0, 1] scale, standardised proprio).

    A linear layer maps the latent to a (4c, b, b) grid with b = ceil(S / 8); three stride-2
    transposed convolutions (4c -> 2c -> c -> c) upsample it to 8b >= S, a 3x3 convolution
    gives the 9 channels, cropped to S x S. An MLP reconstructs the proprio.
    """

    def __init__(
        self, latent_dim: int, image_size: int, proprio_dim: int, channels: int, hidden: int
    ) -> None:
        super().__init__()
        c, self.image_size = channels, image_size
        self.base = math.ceil(image_size / 8)
        self.fc = nn.Sequential(nn.Linear(latent_dim, 4 * c * self.base**2), nn.ReLU())
        self.deconv = nn.Sequential(
            nn.Unflatten(-1, (4 * c, self.base, self.base)),
            nn.ConvTranspose2d(4 * c, 2 * c, 4, stride=2, padding=1), nn.ReLU(),
            nn.ConvTranspose2d(2 * c, c, 4, stride=2, padding=1), nn.ReLU(),
            nn.ConvTranspose2d(c, c, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(c, 9, 3, padding=1),
        )  # fmt: skip
        self.proprio = mlp(latent_dim, [hidden], proprio_dim)

    def forward(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = self.image_size
        # +0.5: an untrained decoder starts at mid-grey, the middle of the [0, 1] range
        img = self.deconv(self.fc(z))[..., :s, :s] + 0.5
        return img, self.proprio(z)


class Autoencoder(nn.Module):
    """The model's pixel encoder (built from `enc_cfg`) and a `PixelDecoder`."""

    def __init__(self, enc_cfg: TDMPC2Config, decoder_channels: int) -> None:
        super().__init__()
        self.encoder = build_encoder(enc_cfg)
        self.decoder = PixelDecoder(
            enc_cfg.latent_dim, enc_cfg.image_size, enc_cfg.proprio_dim, decoder_channels,
            enc_cfg.enc_dim,
        )

    def train(self, mode: bool = True) -> Autoencoder:
        super().train(mode)
        # The encoder's built-in random shift would move the input but not the target; this
        # module's own augmentation shifts both. No dropout or batch norm in the encoder, so
        # eval mode changes nothing else.
        self.encoder.train(False)
        return self

    def forward(
        self, pixels: torch.Tensor, proprio: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decoder(self.encoder({"pixels": pixels, "proprio": proprio}))


# ============================================================================ evaluation


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else 10.0 * math.log10(1.0 / mse)


@torch.no_grad()
def evaluate_reconstruction(
    model: Autoencoder,
    store: FrameStore,
    pairs: np.ndarray,
    proprio_norm: tuple[torch.Tensor, torch.Tensor],
    batch_size: int,
    device: torch.device,
) -> dict | None:
    """Per camera MSE and PSNR (dB, [0, 1] scale, reconstruction clamped to [0, 1]) over the
    frames `pairs`, plus the image and standardised-proprio MSE of the objective."""
    if len(pairs) == 0:
        return None
    was_training = model.training
    model.train(False)
    sq = torch.zeros(len(CAMERAS), dtype=torch.float64)
    obj_img, obj_prop = 0.0, 0.0
    mean, std = proprio_norm
    for start in range(0, len(pairs), batch_size):
        pix, prop = store.batch(pairs[start:start + batch_size])
        pix, prop = torch.from_numpy(pix).to(device), torch.from_numpy(prop).to(device)
        target = pix.float() / 255.0
        rec, rec_prop = model(pix, prop)
        obj_img += F.mse_loss(rec, target, reduction="sum").item()
        obj_prop += F.mse_loss(rec_prop, (prop - mean) / std, reduction="sum").item()
        err = (rec.clamp(0.0, 1.0) - target).square()
        sq += err.unflatten(-3, (len(CAMERAS), 3)).sum(dim=(0, 2, 3, 4)).double().cpu()
    model.train(was_training)
    n = len(pairs)
    s = model.decoder.image_size
    per_cam = (sq / (n * 3 * s * s)).tolist()
    return {
        "frames": n,
        "cameras": {c: {"mse": m, "psnr_db": _psnr(m)} for c, m in zip(CAMERAS, per_cam,
                                                                      strict=True)},
        "image_mse": obj_img / (n * 9 * s * s),
        "proprio_mse": obj_prop / (n * mean.numel()),
    }


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
    """The finished run's record at `out` if it was made with these settings; ValueError if
    `out` holds an encoder made with other settings."""
    weights, side, ckpt = _paths(out)
    if weights.exists() and not side.is_file() and not ckpt.is_file():
        # Ours always has a sidecar, or a checkpoint while the sidecar is being written.
        raise ValueError(f"{weights} exists and is not a pretraining output; choose another --out")
    if not (weights.is_file() and side.is_file()):
        return None
    record = read_encoder_sidecar(weights)
    if record.get("kind") != KIND or record.get("identity") != json.loads(
        json.dumps(config.identity())
    ):
        raise ValueError(
            f"{weights} already holds an encoder pretrained with other settings; choose "
            "another --out or delete it (and its .json sidecar)"
        )
    return record


def _rng_state(rng: np.random.Generator) -> dict:
    state = {"torch": torch.get_rng_state(), "sample": rng.bit_generator.state}
    if torch.cuda.is_available():  # augmentation on a CUDA device draws from its generator
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict, rng: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    rng.bit_generator.state = state["sample"]
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


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
        raise ValueError(f"--out must end in .safetensors, got {out}")
    done = _finished(config, out)
    if done is not None:
        return done["metrics"]
    check_datasets(config)
    threads = torch.get_num_threads()
    if config.torch_threads:
        torch.set_num_threads(config.torch_threads)
    try:
        return _pretrain(config, out, progress, on_step)
    finally:
        torch.set_num_threads(threads)


def _pretrain(
    config: PretrainConfig, out: Path, progress: bool, on_step: Callable | None
) -> dict:
    from tqdm.auto import tqdm

    from ccfit.train import atomic_torch_save, resolve_device

    weights, _, ckpt_path = _paths(out)
    identity = json.loads(json.dumps(config.identity()))
    device = resolve_device(config.device)
    enc_cfg = config.encoder_config()

    store, suites_manifest = load_oracle_frames(config, progress=progress)
    train_eps, held_eps = split_episodes(store.episodes, config.holdout, config.seed)
    train_pairs, held_pairs = store.index(train_eps), store.index(held_eps)
    if len(train_pairs) == 0:
        raise ValueError("no training frames: every episode was held out")
    if progress:
        gb = sum(p.nbytes for p in store.pixels) / 1e9
        print(f"{len(store.episodes)} oracle episodes ({len(held_eps)} held out), "
              f"{len(train_pairs)} training and {len(held_pairs)} held-out frames ({gb:.2f} GB)")
    all_prop = np.concatenate([store.proprio[e] for e in train_eps])
    mean = torch.from_numpy(all_prop.mean(0)).to(device)
    std = torch.from_numpy(all_prop.std(0)).clamp_min(1e-3).to(device)
    rng = np.random.default_rng([config.seed, _SAMPLE_TAG])
    # A fixed sample of training frames, to compare with the held-out error (overfitting).
    train_probe = train_pairs[
        np.sort(np.random.default_rng([config.seed, _SAMPLE_TAG, 1]).permutation(
            len(train_pairs))[: max(len(held_pairs), config.eval_batch_size)])
    ]  # fmt: skip

    torch.manual_seed(config.seed)
    model = Autoencoder(enc_cfg, config.decoder_channels).to(device)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    step, history, window, initial = 0, [], [], None
    if ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if ck.get("version") != CHECKPOINT_VERSION or ck.get("identity") != identity:
            raise ValueError(
                f"{ckpt_path} is a checkpoint of other settings; rerun with those or delete it"
            )
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        _set_rng_state(ck["rng"], rng)
        step, history, initial = int(ck["step"]), ck["history"], ck["initial_heldout"]
        window = list(ck["window"])  # losses since the last history point
    else:
        initial = evaluate_reconstruction(
            model, store, held_pairs, (mean, std), config.eval_batch_size, device
        )

    def save_checkpoint() -> None:
        atomic_torch_save({
            "version": CHECKPOINT_VERSION, "identity": identity, "step": step,
            "model": model.state_dict(), "optimizer": opt.state_dict(),
            "rng": _rng_state(rng), "history": history, "window": window,
            "initial_heldout": initial,
        }, ckpt_path)  # fmt: skip

    start = time.perf_counter()
    bar = tqdm(total=config.steps, initial=step, desc="pretrain-encoder", unit="step",
               disable=not progress)  # fmt: skip
    try:
        while step < config.steps:
            pairs = train_pairs[rng.integers(0, len(train_pairs), config.batch_size)]
            pix, prop = store.batch(pairs)
            pix, prop = torch.from_numpy(pix).to(device), torch.from_numpy(prop).to(device)
            if config.augment_shift > 0:
                pix = random_shift(pix, config.augment_shift)
            rec, rec_prop = model(pix, prop)
            img_loss = F.mse_loss(rec, pix.float() / 255.0)
            prop_loss = F.mse_loss(rec_prop, (prop - mean) / std)
            loss = img_loss + config.proprio_coef * prop_loss
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
        model, store, held_pairs, (mean, std), config.eval_batch_size, device
    )
    train_eval = evaluate_reconstruction(
        model, store, train_probe, (mean, std), config.eval_batch_size, device
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


# ================================================================================== CLI


def add_pretrain_parser(subparsers) -> argparse.ArgumentParser:
    """Register `pretrain-encoder` on an argparse subparsers object; its handler is
    `args.func(args)` and raises ValueError (one clear message) on bad input."""
    p = subparsers.add_parser(
        "pretrain-encoder",
        help="pretrain the frozen encoder (autoencoder on every task's oracle episodes)",
    )
    p.add_argument("--suites", default="all", help="'all' or a comma list, e.g. Reach,Grasp")
    p.add_argument("--preset", default="cpu", help="smoke | cpu | paper (default cpu); the "
                   "encoder's sizes follow the TD-MPC2 preset of the same name")  # fmt: skip
    p.add_argument("--out", default=None,
                   help="weights file (default runs/encoders/encoder-PRESET-sSEED.safetensors)")
    p.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, default=64, help="camera image side of the datasets")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_pretrain)
    return p


def config_from_args(args: argparse.Namespace) -> PretrainConfig:
    """The PretrainConfig of a parsed `pretrain-encoder` command line."""
    overrides: dict[str, Any] = {"suites": args.suites, "seed": args.seed,
                                 "image_size": args.image_size, "device": args.device}
    if args.steps is not None:
        overrides["steps"] = args.steps
    return PretrainConfig.preset(args.preset, **overrides)


def _cmd_pretrain(args: argparse.Namespace) -> None:
    config = config_from_args(args)
    out = Path(args.out or f"runs/encoders/encoder-{args.preset}-s{args.seed}.safetensors")
    metrics = pretrain_encoder(config, out, progress=not args.quiet)
    held = metrics.get("heldout")
    if held:
        cams = ", ".join(f"{c} {v['psnr_db']:.1f} dB" for c, v in held["cameras"].items())
        print(f"held-out reconstruction PSNR: {cams}  ->  {out}")
    else:
        print(f"no held-out episodes  ->  {out}")
