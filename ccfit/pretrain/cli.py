"""`ccfit pretrain-encoder`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ccdata.errors import add_command
from ccfit.models import DEFAULT_MODEL
from ccfit.pretrain.config import PretrainConfig
from ccfit.pretrain.train import pretrain_encoder

# ================================================================================== CLI

_TRAINING_OVERRIDES = {"steps": int, "batch_size": int, "lr": float, "decoder_channels": int,
                       "augment_shift": int, "policies": str, "explore_frame_stride": int,
                       "foreground_weight": float, "foreground_threshold": float,
                       "keypoints": int, "image_trunk": str, "contrastive_coef": float,
                       "contrastive_temperature": float, "proprio_coef": float,
                       "batch_from": str}  # fmt: skip
"""PretrainConfig fields a command line may set over the preset's values (see its docstrings)."""


def add_pretrain_parser(subparsers) -> argparse.ArgumentParser:
    """Register `pretrain-encoder` on an argparse subparsers object; its handler is
    `args.func(args)` and raises InputError (one clear message) on bad input."""
    p = add_command(
        subparsers,
        "pretrain-encoder",
        "pretrain the frozen encoder (every task's episodes: reconstruction and an "
        "episode-contrastive term, docs/encoder.md)",
        "ccfit pretrain-encoder --suites all --out enc.safetensors",
    )
    p.add_argument("--suites", default="all", help="'all' or a comma list, e.g. Reach,Grasp")
    p.add_argument("--preset", default="cpu", help="smoke | cpu | paper (default cpu); the "
                   "encoder's sizes follow the model's preset of the same name")  # fmt: skip
    # `--model.type` as `ccfit run` and `fit` spell it; `--model` as scripts have spelt it
    p.add_argument("--model.type", "--model", dest="model", default=DEFAULT_MODEL,
                   help="the world model whose pixel encoder is pretrained (one offering "
                        "'pixel-encoder')")  # fmt: skip
    p.add_argument(
        "--out",
        default=None,
        help="weights file (default runs/encoders/encoder-PRESET-sSEED.safetensors)",
    )
    for name, kind in _TRAINING_OVERRIDES.items():
        p.add_argument(f"--{name.replace('_', '-')}", type=kind, default=None,
                       help=f"override the preset's {name}")  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, default=64, help="camera image side of the datasets")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--torch-threads", type=int, default=None,
                   help="CPU threads for torch (default 1; 0: torch's default), as "
                        "--train.torch_threads")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_pretrain)
    return p


def config_from_args(args: argparse.Namespace) -> PretrainConfig:
    """The PretrainConfig of a parsed `pretrain-encoder` command line."""
    overrides: dict[str, Any] = {
        "model": args.model,
        "suites": args.suites,
        "seed": args.seed,
        "image_size": args.image_size,
        "device": args.device,
    }
    if args.torch_threads is not None:
        overrides["torch_threads"] = args.torch_threads
    for name in _TRAINING_OVERRIDES:
        if getattr(args, name) is not None:
            overrides[name] = getattr(args, name)
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
