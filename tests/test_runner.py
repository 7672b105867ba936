"""The curriculum runner tested with a track that counts calls: the order it asks a track for
what, resuming after the last finished task, the shared reference learnt once, the metrics.
No environment and no dataset: a third track would meet the same runner."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import test_seam  # noqa: F401 - registers the toy model
import torch

from ccfit.config import CurriculumConfig
from ccfit.config_parse import resolve
from ccfit.models.registry import make_model
from ccfit.run_files import METRICS_JSON, REFERENCE_DONE
from ccfit.runner import CurriculumRunner, Restored, Track
from ccfit.train.records import RunLogger

STEPS = 10


class Stop(Exception):
    """Raised by the counting track to stop a run right after a state was saved."""


class CountingTrack(Track):
    """Learns a task by moving the backbone with random numbers from the global generator
    (so an exact resume needs the RNG state the runner saves) and logs one record per task
    seen so far at the task's start and end, as the online track's evaluations do."""

    name, loop = "counting", "train"
    state_file, state_kind, state_version = "counting.pt", "test-counting", 1
    config_class = CurriculumConfig

    def __init__(self, cfg: CurriculumConfig, calls: list, stop_at: int | None = None) -> None:
        super().__init__(cfg)
        self.calls, self.stop_at = calls, stop_at

    @property
    def budget(self) -> int:
        return STEPS

    def resolved_config(self, *, record_dataset: bool = True) -> dict:
        return self.cfg.to_dict()

    def begin(self, out: Path, progress: bool) -> dict:
        self.out = out
        self.calls.append("begin")
        out.mkdir(parents=True, exist_ok=True)
        return self.resolved_config()

    def build_model(self, device: torch.device, resolved: dict | None):
        return make_model(self.cfg.model, device)

    def open(self, resolved: dict, restored: Restored) -> RunLogger:
        self.calls.append(f"open after {restored.completed}")
        self.model = restored.model
        self.logger = RunLogger(self.out, self.cfg.log)
        return self.logger

    def _log(self, task: int, stage: int, step: int) -> None:
        score = float(sum(p.detach().sum() for p in self.model.backbone.parameters()))
        with self.logger.jsonl.open("a") as f:
            f.write(json.dumps({"task": self.cfg.tasks[task], "task_index": task,
                                "stage": stage, "global_step": step, "task_step": step % STEPS,
                                "normalized_return": score}) + "\n")  # fmt: skip

    def learn_task(self, index, folder, resumed, backbone_optim):
        self.calls.append(f"learn {index}")
        self._log(index, index, index * STEPS)
        with torch.no_grad():
            for p in self.model.backbone.parameters():
                p.add_(torch.randn_like(p))
        for j in range(index + 1):
            self._log(j, index, (index + 1) * STEPS)
        return torch.optim.SGD(self.model.backbone.parameters(), lr=0.1)

    def close_task(self, index: int) -> dict:
        self.calls.append(f"close {index}")
        return {"heads": []}

    def saved(self, state: Path, completed: int) -> None:
        self.calls.append(f"saved {completed}")
        if completed == self.stop_at:
            raise Stop

    def finish(self) -> None:
        self.calls.append("finish")

    def close(self) -> None:
        self.calls.append("close")
        self.logger.close()

    def describe(self) -> dict:
        return {"track": self.name, "method": self.cfg.method.type}

    def learn_reference(self, out: Path, progress: bool) -> list[dict]:
        self.calls.append("reference")
        n = len(self.cfg.tasks) - 1
        return [{"task": self.cfg.tasks[n], "task_index": n, "stage": n, "global_step": step,
                 "task_step": step, "normalized_return": 0.0} for step in (0, STEPS)]  # fmt: skip


def _config(method: str = "ft") -> CurriculumConfig:
    return resolve(CurriculumConfig, {
        "suite": "Reach", "preset": "smoke", "seed_dataset": None, "model": {"type": "toy"},
        "method": {"type": method}, "log": {"tensorboard": False},
    })  # fmt: skip


def test_the_runner_asks_a_track_in_order_and_learns_the_reference_once(tmp_path):
    calls: list[str] = []
    cfg = _config()
    result = CurriculumRunner(CountingTrack(cfg, calls), tmp_path / "run").run()
    tasks = [f"{what} {i}" for i in range(4) for what in ("learn", "close")]
    saves = [f"saved {k}" for k in range(1, 5)]
    assert calls == ["begin", "open after 0",
                     *[c for i in range(4) for c in (tasks[2 * i], tasks[2 * i + 1], saves[i])],
                     "finish", "close", "reference"]  # fmt: skip
    assert json.loads((tmp_path / "run" / METRICS_JSON).read_text()) == json.loads(
        json.dumps(result)
    )
    assert result["track"] == "counting" and len(result["end_of_task"]) == 4
    reference = Path(result["scratch_dir"])
    assert reference.parent == tmp_path / "scratch" and (reference / REFERENCE_DONE).is_file()
    # Another method's run has the same key: it reads the reference and learns none.
    calls.clear()
    other = CurriculumRunner(CountingTrack(_config("ewc"), calls), tmp_path / "ewc").run()
    assert "reference" not in calls and other["scratch_dir"] == result["scratch_dir"]
    assert not list((tmp_path / "run").glob("tasks/*")), "each task's folder is removed"


def test_a_run_stopped_after_a_task_resumes_at_the_next_to_the_same_end(tmp_path):
    whole: list[str] = []
    ended = CurriculumRunner(CountingTrack(_config(), whole), tmp_path / "whole").run()
    stopped: list[str] = []
    with pytest.raises(Stop):
        CurriculumRunner(CountingTrack(_config(), stopped, stop_at=2), tmp_path / "run").run()
    assert stopped[-2:] == ["saved 2", "close"], "the track is closed when a task fails"
    resumed: list[str] = []
    again = CurriculumRunner(CountingTrack(_config(), resumed), tmp_path / "run").run()
    assert resumed[:3] == ["begin", "open after 2", "learn 2"]
    assert again["end_of_task"] == ended["end_of_task"]
    assert [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
            ] == [json.loads(x) for x in (tmp_path / "whole" / "metrics.jsonl").read_text()
                  .splitlines()]  # fmt: skip
