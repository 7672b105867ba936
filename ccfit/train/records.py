"""Run records: evaluation records to JSONL (one line per evaluation, always), and scalars to
TensorBoard and, when asked for, Weights & Biases (`LogConfig`)."""

from __future__ import annotations

import json
import secrets
from collections.abc import Sequence
from pathlib import Path

from ccdata.errors import InputError
from ccdata.processes import one_line
from ccfit.config import LogConfig
from ccfit.io import atomic_write_text, read_run_json
from ccfit.run_files import METRICS_JSONL

METRICS = METRICS_JSONL
TENSORBOARD = "tb"
WANDB_ID = "wandb_id"
"""File in the run directory holding its W&B run id, so a resumed run continues the same W&B
run."""


class RunLogger:
    """Evaluation records in `run_dir/metrics.jsonl`; scalars in `run_dir/tb` and on W&B.

    log: where scalars go (None: TensorBoard only); config: what W&B records as the run's
    config (the resolved config.json). A resumed run rewinds TensorBoard to its checkpoint;
    W&B keeps the steps it has already received, so it holds the first values of steps that a
    resumed run does again.
    """

    def __init__(self, run_dir: str | Path, log: LogConfig | None = None,
                 config: dict | None = None) -> None:  # fmt: skip
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = self.run_dir / METRICS
        self.log = log if log is not None else LogConfig()
        self.config = config
        self._tb = None
        self._wandb = None
        text = self.jsonl.read_text() if self.jsonl.exists() else ""
        if text and not text.endswith("\n"):
            # An append cut short (the machine went down mid-write): drop the partial record,
            # which its resumed run logs again, before anything is appended after it.
            atomic_write_text(self.jsonl, "".join(x + "\n" for x in text.splitlines()[:-1]))
        if self.log.wandb:  # now, so that missing credentials stop the run before it trains
            self._start_wandb()

    def _writer(self, purge_step: int | None = None):
        if self._tb is None and self.log.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.run_dir / TENSORBOARD), purge_step=purge_step)
        return self._tb

    def _start_wandb(self) -> None:
        import wandb

        try:
            self._wandb_run()
        except wandb.errors.Error as err:  # no API key, an unreachable or refusing server
            raise InputError(
                f"log.wandb: W&B could not start a run: {one_line(err)} (--log.wandb_mode="
                "offline writes it under the run's folder for `wandb sync` later)"
            ) from None

    def _wandb_run(self):
        if self._wandb is None and self.log.wandb:
            import wandb

            id_file = self.run_dir / WANDB_ID
            if not id_file.is_file():
                atomic_write_text(id_file, secrets.token_hex(8) + "\n")
            log = self.log
            self._wandb = wandb.init(
                project=log.wandb_project, entity=log.wandb_entity, group=log.wandb_group,
                mode=log.wandb_mode, dir=str(self.run_dir), name=self.run_dir.name,
                id=id_file.read_text().strip(), resume="allow", config=self.config,
                settings=wandb.Settings(silent=True, console="off"),
            )  # fmt: skip
        return self._wandb

    def keep(self, predicate) -> None:
        """Drop the records for which `predicate(record)` is false (atomically)."""
        records = self.read_evals()
        kept = [r for r in records if predicate(r)]
        if len(kept) != len(records):
            write_records(self.jsonl, kept)

    def rewind(self, global_step: int) -> None:
        """Forget what was logged after `global_step` (a resumed run redoes those steps)."""
        self.keep(lambda r: r["global_step"] <= global_step)
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        self._writer(purge_step=global_step + 1)

    def settle(self, requests: Sequence[dict]) -> tuple[list[dict], list[dict]]:
        """Evaluation requests a checkpoint lists as in flight (their records may have come in
        after it was written): (the records of those logged whole, the requests to submit
        again). The records of a request logged in part are dropped."""
        logged = {_key(r): r for r in self.read_evals()}
        done, again, partial = [], [], set()
        for request in requests:
            keys = [(request["global_step"], request["stage"], t) for t in request["tasks"]]
            have = [k for k in keys if k in logged]
            if len(have) == len(keys):
                done += [logged[k] for k in keys]
            else:
                again.append(request)
                partial.update(have)
        if partial:
            self.keep(lambda r: _key(r) not in partial)
        return done, again

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
        run = self._wandb_run()
        if run is not None:
            run.log({**scalars, "global_step": step}, step=step)

    def read_evals(self) -> list[dict]:
        if not self.jsonl.exists():
            return []
        # a cut last line (a kill) is mended before this; any other damage is refused
        return read_run_json(self.jsonl, lines=True, remedy="the run cannot be read back; "
                             "delete its folder to start it over")  # fmt: skip

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        if self._wandb is not None:
            self._wandb.finish()
            self._wandb = None


def write_records(path: Path, records: Sequence[dict]) -> None:
    """`records` as a run's metrics.jsonl (one JSON object a line), written atomically."""
    atomic_write_text(path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))


def record_stage(record: dict) -> int:
    """The task being trained when `record` was evaluated (records older than the field: its
    own task's)."""
    return int(record.get("stage", record["task_index"]))


def _key(record: dict) -> tuple[int, int, int]:
    """An evaluation record's identity: global step, stage (task being trained), task."""
    return record["global_step"], record_stage(record), record["task_index"]
