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

import contextlib
import functools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ccfit.config_base import ConfigError, check, resolve_device

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


def check_compile_device(setting: str, device: torch.device) -> None:
    """Refuse `--train.compile=graphs` where there is no CUDA device to replay graphs on."""
    if setting == "graphs" and torch.device(device).type != "cuda":
        raise ConfigError(f"train.compile=graphs replays CUDA graphs: it needs a CUDA "
                          f"device, and this run's is {device}; use --train.compile=auto or "
                          "on")  # fmt: skip


_BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})
"""x86 CPU flags of bf16 dot-product instructions (AVX512-BF16, AMX): without them oneDNN
emulates bf16 matmuls and they are no faster than float32."""


@functools.cache
def cpu_info() -> dict[str, str]:
    """The first processor's fields in Linux's /proc/cpuinfo ('model name', 'flags', ...),
    read once; empty elsewhere."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_flags() -> frozenset[str]:
    """This machine's CPU feature flags (x86 'flags', Arm 'Features'; empty where unknown)."""
    info = cpu_info()
    return frozenset(info.get("flags", info.get("Features", "")).split())


def native_bf16(device: torch.device, flags: frozenset[str] | None = None) -> bool:
    """Whether `device` multiplies bfloat16 matrices in hardware: a CUDA GPU of compute
    capability 8.0 or more, or a CPU with AVX512-BF16 or AMX (`flags`: this CPU's)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    if device.type == "cpu":
        return bool(_BF16_CPU_FLAGS & (cpu_flags() if flags is None else flags))
    return False


def resolve_autocast(setting: str, device: torch.device) -> str:
    """'off' or 'bf16': what `--train.autocast` means on `device`. 'auto' is bf16 where the
    hardware multiplies in bf16 (`native_bf16`). On a 2-core AVX512-BF16 CPU, TD-MPC2's
    compiled update and plan at 1M and 5M (batch 256) measured 1.8-2.9x faster in bf16 than in
    float32 (bench/update_rate.py), while the small `cpu` sizes, bound by dispatch overhead,
    gain nothing (so that preset stays 'off')."""
    if setting == "auto":
        return "bf16" if native_bf16(device) else "off"
    return setting


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block on `count` CPU threads for torch (0: leave torch's setting), and give
    torch back the count it had (a command run in-process, e.g. from the tests, leaves no
    trace)."""
    before = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
