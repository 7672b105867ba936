"""Run records: evaluation records to JSONL (one line per evaluation), scalars to TensorBoard."""

from __future__ import annotations

import json
from pathlib import Path

from ccfit.io import atomic_write_text

METRICS = "metrics.jsonl"
TENSORBOARD = "tb"


class RunLogger:
    """Evaluation records in `run_dir/metrics.jsonl` and scalars in `run_dir/tb`."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = self.run_dir / METRICS
        self._tb_enabled = tensorboard
        self._tb = None

    def _writer(self, purge_step: int | None = None):
        if self._tb is None and self._tb_enabled:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.run_dir / TENSORBOARD), purge_step=purge_step)
        return self._tb

    def keep(self, predicate) -> None:
        """Drop the records for which `predicate(record)` is false (atomically)."""
        records = self.read_evals()
        kept = [r for r in records if predicate(r)]
        if len(kept) != len(records):
            atomic_write_text(self.jsonl, "".join(json.dumps(r, sort_keys=True) + "\n"
                                                  for r in kept))  # fmt: skip

    def rewind(self, global_step: int) -> None:
        """Forget what was logged after `global_step` (a resumed run redoes those steps)."""
        self.keep(lambda r: r["global_step"] <= global_step)
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        self._writer(purge_step=global_step + 1)

    def log_eval(self, record: dict) -> None:
        with self.jsonl.open("a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")
        tag = record["task"]
        scalars = {
            f"eval/{tag}/discounted_return": record["discounted_return"],
            f"eval/{tag}/success_rate": record["success_rate"],
        }
        if record["normalized_return"] is not None:
            scalars[f"eval/{tag}/normalized_return"] = record["normalized_return"]
        self.log_scalars(scalars, record["global_step"])

    def log_scalars(self, scalars: dict[str, float], step: int) -> None:
        writer = self._writer()
        if writer is not None:
            for k, v in scalars.items():
                writer.add_scalar(k, v, step)

    def read_evals(self) -> list[dict]:
        if not self.jsonl.exists():
            return []
        return [json.loads(x) for x in self.jsonl.read_text().splitlines() if x.strip()]

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None
