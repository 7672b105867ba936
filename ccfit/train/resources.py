"""Memory and disk a run needs, checked before it starts; where its replay lives.

`--preset paper --obs pixels` asks for a million 64 px rows of replay per task (37 GB); a run
that cannot hold it should say so at once, naming the setting to lower, not fail hours in.
Replay is the one large allocation: a row holds an observation as replay stores it (frames,
or a frozen encoder's latents) and a transition. It lives on the training GPU when it fits
there with room to spare (batches are then drawn where they are used), else in host memory,
page-locked when a GPU reads it. Its rows are also what checkpoints write to the run
directory (incrementally, `ccfit.replay_store`), so the disk must hold them too.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import torch

from ccfit.config import RunConfig
from ccfit.config_base import ConfigError
from ccfit.models.base import WorldModel
from ccfit.replay_store import disk_rows

GPU_SHARE = 0.5
"""Replay goes on the GPU when it takes at most this share of the GPU's free memory."""
HOST_SHARE = 0.8
"""A run is refused when replay would take more than this share of the available memory."""
TRANSITION_BYTES = 4 * 4 + 4 + 4 + 1 + 8
"""Action (4 x float32), reward, terminated (float32), is_first (bool), task (int64)."""


@dataclass(frozen=True)
class ReplayPlan:
    row_bytes: int
    capacity: int
    demo_rows: int
    """Rows of demonstrations kept beside the ring (`--train.demo_fraction`)."""
    storage: torch.device

    @property
    def bytes(self) -> int:
        """Memory: the ring's rows and the demonstrations kept beside it."""
        return self.row_bytes * (self.capacity + self.demo_rows)


def row_bytes(cfg: RunConfig, model: WorldModel) -> int:
    """Bytes of one replay row of this run: an observation as the model has replay store it
    (`WorldModel.replay_obs`), plus the transition."""
    m = cfg.model
    if cfg.obs == "state":
        obs = {"state": torch.zeros(1, m.state_dim)}
    else:
        size = cfg.image_size
        obs = {"pixels": torch.zeros(1, 9, size, size, dtype=torch.uint8),
               "proprio": torch.zeros(1, m.proprio_dim)}  # fmt: skip
    stored = model.replay_obs(obs)
    return sum(v[0].numel() * v.element_size() for v in stored.values()) + TRANSITION_BYTES


def available_host_memory() -> int:
    """MemAvailable of /proc/meminfo (bytes)."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no MemAvailable in /proc/meminfo")


def plan_replay(cfg: RunConfig, model: WorldModel, demo_rows: int = 0) -> ReplayPlan:
    """Where this run's replay goes, or ConfigError when it fits nowhere. demo_rows: the
    demonstrations a task's buffer keeps beside its ring (`seeding.demonstration_rows`; only
    with `--train.demo_fraction`)."""
    row = row_bytes(cfg, model)
    total = row * (cfg.train.buffer_capacity + demo_rows)
    device = model.device
    if device.type == "cuda" and total <= GPU_SHARE * torch.cuda.mem_get_info(device)[0]:
        return ReplayPlan(row, cfg.train.buffer_capacity, demo_rows, device)
    free = available_host_memory()
    if total > HOST_SHARE * free:
        demos = f" and {demo_rows} rows of demonstrations" if demo_rows else ""
        most = int(HOST_SHARE * free // row) - demo_rows
        fix = (f"lower --train.buffer_capacity to at most {most}" if most >= 2 else
               "set --train.demo_fraction=0 (the demonstrations alone do not fit)")  # fmt: skip
        raise ConfigError(
            f"replay needs {_gb(total)} ({cfg.train.buffer_capacity} rows{demos} of {row} B) "
            f"but {_gb(free)} of memory is available: {fix}"
        )
    return ReplayPlan(row, cfg.train.buffer_capacity, demo_rows, torch.device("cpu"))


def check_disk(plan: ReplayPlan, out: Path) -> None:
    """ConfigError unless the run directory's filesystem can hold replay's row files at their
    largest (`replay_store.disk_rows`: what the checkpoints of one task keep at once)."""
    out = Path(out)
    probe = next(p for p in [out, *out.parents] if p.exists())
    free = shutil.disk_usage(probe).free
    need = plan.row_bytes * disk_rows(plan.capacity, plan.demo_rows)
    if need > free:
        most = _largest(lambda c: plan.row_bytes * disk_rows(c, plan.demo_rows) <= free)
        fix = (f"lower --train.buffer_capacity to at most {most} or use another --out"
               if most >= 2 else "use another --out")  # fmt: skip
        raise ConfigError(f"checkpoints of a task keep up to {_gb(need)} of replay in {out} "
                          f"but {_gb(free)} is free there: {fix}")  # fmt: skip


def _largest(fits) -> int:
    """The largest n >= 0 with fits(n), for `fits` true up to some n and false after."""
    low, high = 0, 1
    while fits(high):
        low, high = high, 2 * high
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (mid, high) if fits(mid) else (low, mid)
    return low


def _gb(n: int) -> str:
    return f"{n / 1e9:.1f} GB"
