"""How a run executes where it runs: its device, compile mode, precision and CPU threads,
resolved once from the config's settings (`resolve_execution`) into a frozen `Execution`
that is recorded in config.json and handed down to what builds and steps the model.

Both tracks and pretraining name these settings alike (`--train.*` online, `--fit.*`
offline, `--device`/`--torch_threads` in `ccfit pretrain-encoder`): `device`,
`torch_threads`, and where the loop has them `compile` and `autocast`. Nothing below this
module resolves a device name or an 'auto' again: a model takes a `torch.device`, the update
step and the evaluator the resolved precision.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import torch

from ccfit.config_base import check, resolve_device

AUTOCAST_MODES: tuple[str, ...] = ("off", "bf16")
"""What `--train.autocast` resolves to (`resolve_autocast`): float32, or bfloat16 autocast."""
DEVICE_NAME = re.compile(r"auto|cpu|cuda(:\d+)?")
"""Device names a config accepts: 'auto', 'cpu', 'cuda' or 'cuda:N' (the N-th GPU)."""


def check_device_name(name: Any, where: str) -> None:
    """ConfigError unless `name` is a device name a config accepts (`DEVICE_NAME`). No I/O:
    whether the device is here is asked when the run starts (`resolve_execution`)."""
    check(isinstance(name, str) and DEVICE_NAME.fullmatch(name) is not None,
          f"{where} must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}")  # fmt: skip


@dataclass(frozen=True)
class Execution:
    """How a run executes: resolved from its loop's settings once per process
    (`resolve_execution`); part of config.json through `records`."""

    device: torch.device
    """Where the model lives and computes ('auto' resolved: CUDA when available)."""
    compile: str = "off"
    """The compile setting ('off', 'on', 'graphs', 'auto'): which hot paths compile is
    decided with the model class and the run's length (`ccfit.train.compiled`), and recorded
    as `resolved_compile`; 'graphs' also marks each update as a CUDA-graph step."""
    autocast: str = "off"
    """The precision of updates and acting, resolved: 'off' (float32) or 'bf16'."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default, left alone)."""

    def __post_init__(self) -> None:
        check(
            isinstance(self.device, torch.device),
            f"Execution.device must be a torch.device, got {self.device!r}",
        )
        check(self.autocast in AUTOCAST_MODES,
              f"Execution.autocast must be resolved to one of {AUTOCAST_MODES}, got "
              f"{self.autocast!r} (resolve_execution resolves 'auto')")  # fmt: skip

    @property
    def graphs(self) -> bool:
        """The hot paths replay CUDA graphs (`--train.compile=graphs`)."""
        return self.compile == "graphs"

    def autocast_context(self) -> torch.autocast:
        """The autocast context of the run's precision (a no-op context for 'off')."""
        return autocast_context(self.device, self.autocast)

    def set_threads(self) -> None:
        """Give torch the run's CPU threads (nothing for 0: torch's default)."""
        if self.torch_threads > 0:
            torch.set_num_threads(self.torch_threads)

    def records(self) -> dict:
        """What config.json records of it (the keys runs have always recorded)."""
        return {"resolved_device": str(self.device), "resolved_autocast": self.autocast}


def autocast_context(device: torch.device, mode: str) -> torch.autocast:
    """torch's autocast on `device` for a resolved precision `mode` (`AUTOCAST_MODES`)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=mode == "bf16")


def resolve_execution(loop: Any, device: str | torch.device | None = None) -> Execution:
    """The `Execution` of a loop's settings (`TrainConfig`, `FitConfig`, `PretrainConfig`:
    `device`, `torch_threads`, and `compile`/`autocast` where it has them, else 'off'):
    the one place a device name and 'auto' are resolved. `device`: another device than the
    config's, for a run read back (analyses load GPU runs on a CPU: its compile setting is
    then taken as it is, as loading always did). ConfigError, in one line, for a device that
    is not here (CUDA absent, `cuda:N` past the GPUs), or for a run's own graphs without
    CUDA."""
    from ccfit.train.compiled import check_compile_device, resolve_autocast

    dev = resolve_device(loop.device if device is None else device)
    if dev.type == "cuda" and dev.index is not None:
        count = torch.cuda.device_count()
        check(dev.index < count, f"device {str(dev)!r} requested but this machine has "
                                 f"{count} CUDA device(s); use 'cuda' or 'cuda:0'")  # fmt: skip
    compile_setting = getattr(loop, "compile", "off")
    if device is None:
        check_compile_device(compile_setting, dev)
    return Execution(device=dev, compile=compile_setting,
                     autocast=resolve_autocast(getattr(loop, "autocast", "off"), dev),
                     torch_threads=loop.torch_threads)  # fmt: skip
