"""The commands that made a folder of published runs, for its results page
(`ccfit.report.page`): the datasets and frozen encoders the runs read, and each sweep's
`ccfit sweep` and `ccfit publish`, read from what the runs and sweeps recorded."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

from ccdata.suites import SUITES
from ccfit.pretrain.config import LEGACY_SETTINGS
from ccfit.run_files import PROBED_ENCODER, REPORT, SWEEP_JSON


def published_folders(root: Path) -> list[Path]:
    """The published folders under `root`: those holding a report."""
    return sorted(p.parent for p in root.rglob(REPORT) if p.is_dir())


def sweep_grids(root: Path) -> dict[Path, dict]:
    """Every published sweep folder under `root` -> the grid its sweep.json records, online
    folders first."""
    paths = sorted(root.rglob(SWEEP_JSON), key=lambda p: (p.parent.parent.name != "online", p))
    return {p.parent: json.loads(p.read_text())["grid"] for p in paths}


def frozen_encoders(run_groups: dict) -> set[str]:
    """The frozen encoder files the runs read (`--encoder frozen:NAME`)."""
    return {str(r.config["encoder"]).removeprefix("frozen:")
            for runs in run_groups.values() for r in runs
            if str(r.config.get("encoder") or "").startswith("frozen:")}  # fmt: skip


def _wrapped(words: list[str]) -> list[str]:
    """A command over lines of about 92 characters, each new line at an option."""
    chunks, line = [], words[0]
    for word in map(shlex.quote, words[1:]):
        if len(line) + len(word) > 92 and word.startswith("--"):
            chunks.append(line + " \\")
            line = "   "
        line += " " + word
    return chunks + [line]


ENCODER_OPTIONS = ("steps", "batch_size", "lr", "decoder_channels", "augment_shift", "seed",
                   "image_size", "proprio_coef", *LEGACY_SETTINGS, "explore_frame_stride",
                   "foreground_threshold", "contrastive_temperature")  # fmt: skip
"""The settings of an encoder's sidecar (`encoder.json`) that `ccfit pretrain-encoder` takes,
each given explicitly: the presets' values change, the command must not. A sidecar made before
a setting existed was made at its `LEGACY_SETTINGS` value; one a setting depends on (the
foreground threshold on its weight, ...) is left out where the sidecar has none."""


def _encoder_option(config: dict, option: str) -> list[str]:
    """`--option VALUE` of a sidecar's recorded `config` (`ENCODER_OPTIONS`)."""
    if option not in config and option not in LEGACY_SETTINGS:
        return []
    value = config.get(option, LEGACY_SETTINGS.get(option))
    text = ",".join(map(str, value)) if isinstance(value, list | tuple) else str(value)
    return [f"--{option.replace('_', '-')}", text]


def setup_commands(run_groups: dict, root: Path) -> list[str]:
    """The datasets the published runs read (`ccdata generate`, its defaults) and the frozen
    encoders they read, pretrained with the settings their probe folder's sidecar records."""
    suites = {
        r.config["suite"]
        for runs in run_groups.values()
        for r in runs
        if r.config.get("resolved_seed_dataset") or r.config.get("resolved_dataset")
    }
    encoders = frozen_encoders(run_groups)
    lines = []
    for name in sorted(encoders):
        sidecar = root / "probe" / Path(name).stem / PROBED_ENCODER
        if not sidecar.is_file():
            lines.append(f"# {name}: a frozen encoder whose settings are not published here")
            continue
        config = json.loads(sidecar.read_text())["config"]
        suites |= set(config["suites"])
        words = ["ccfit", "pretrain-encoder", "--suites", ",".join(config["suites"]),
                 "--preset", config["model_preset"], "--model.type", config["model"]]  # fmt: skip
        for option in ENCODER_OPTIONS:
            words += _encoder_option(config, option)
        lines += _wrapped([*words, "--out", name])
    generate = [f"ccdata generate --suite {s}" for s in SUITES if s in suites]
    return generate + lines


def sweep_commands(root: Path) -> list[str]:
    """The `ccfit sweep` and `ccfit publish` commands that made every published sweep, from
    the grid and run options each sweep.json records."""
    lines, grids = [], sweep_grids(root)
    for folder, grid in grids.items():
        rel = folder.relative_to(root)
        args = ["--suites", ",".join(grid["suites"])]
        if grid["models"]:
            args += ["--models", ",".join(grid["models"])]
        seeds = ",".join(map(str, grid["seeds"]))
        args += ["--methods", ",".join(grid["methods"]), "--seeds", seeds,
                 "--preset", grid["preset"]]  # fmt: skip
        if grid["track"] != "online":
            args += ["--track", grid["track"]]
        args += [*grid["args"], "--out", f"../runs/results/{folder.name}"]
        lines += _wrapped(["ccfit", "sweep", *args])
        lines.append(f"ccfit publish ../runs/results/{folder.name} --out {root.name}/{rel} "
                     f"--root {root.name}")  # fmt: skip
    for folder in published_folders(root):
        if folder not in grids:
            lines.append(f"# {folder.relative_to(root)}: published without its sweep's "
                         "record; each run again: ccfit run --config_path RUN/config.json "
                         "--out DIR")  # fmt: skip
    return lines
