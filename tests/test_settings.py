"""How a run executes (`ccfit.settings`): resolved once into a frozen `Execution` that is
recorded and handed down; device names validated without asking the machine, resolved (and
refused, in one line) when the run starts; validation that reads no file; the run's
observation mode and image size held once."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from ccfit.config import CurriculumConfig, TaskRunConfig, TrainConfig, with_encoder
from ccfit.config_base import ConfigError, identity
from ccfit.config_parse import flatten, parse_cli, resolve, saved_config
from ccfit.offline.config import FitConfig
from ccfit.pretrain.config import PretrainConfig
from ccfit.settings import Execution, resolve_execution

try:
    from short_episodes import short
except ImportError:  # run from the repository root
    from tests.short_episodes import short

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ROOT / "results/online/reach-tdmpc2/Reach-tdmpc2-ft-state-cpu-s0/config.json"


def test_the_execution_is_frozen_and_takes_resolved_values_only():
    execution = resolve_execution(TrainConfig(device="cpu", autocast="off", compile="auto"))
    assert execution == Execution(torch.device("cpu"), compile="auto", autocast="off",
                                  torch_threads=1)  # fmt: skip
    assert execution.records() == {"resolved_device": "cpu", "resolved_autocast": "off"}
    with pytest.raises(dataclasses.FrozenInstanceError):
        execution.device = torch.device("meta")  # type: ignore[misc]
    with pytest.raises(ConfigError, match="resolved to one of"):
        Execution(torch.device("cpu"), autocast="auto")
    with pytest.raises(ConfigError, match="must be a torch.device"):
        Execution("cpu")  # type: ignore[arg-type]


@pytest.mark.parametrize("device", ["auto", "cpu", "cuda", "cuda:0", "cuda:1", "cuda:12"])
def test_every_loop_accepts_the_same_device_names(device):
    """`cuda:N` was handled by the resolver but refused by the configs; validation asks
    nothing of the machine."""
    assert TrainConfig(device=device).device == device
    assert FitConfig(device=device).device == device
    assert PretrainConfig(device=device, model_preset="smoke").device == device


@pytest.mark.parametrize("device", ["tpu", "cuda:", "cuda:x", "cuda1", "CPU", ""])
def test_a_bad_device_name_is_refused_by_validation(device):
    with pytest.raises(ConfigError, match="train.device must be 'auto', 'cpu', 'cuda' or"):
        TrainConfig(device=device)
    with pytest.raises(ConfigError, match="fit.device must be"):
        FitConfig(device=device)


def test_a_cuda_device_without_cuda_is_refused_in_one_line_when_the_run_starts(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for loop in (TrainConfig(device="cuda:1"), FitConfig(device="cuda"),
                 PretrainConfig(device="cuda:0", model_preset="smoke")):  # fmt: skip
        with pytest.raises(ConfigError) as err:
            resolve_execution(loop)
        assert "CUDA is not available" in str(err.value) and "\n" not in str(err.value)
    # past the GPUs there are
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ConfigError, match=r"'cuda:1' requested but this machine has 1 CUDA"):
        resolve_execution(TrainConfig(device="cuda:1"))


def test_auto_resolves_once_to_what_the_machine_has(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    execution = resolve_execution(TrainConfig(device="auto", autocast="off"))
    assert execution.device == torch.device("cpu")
    # a run read back on another device than its config's
    assert resolve_execution(TrainConfig(device="cuda"), "cpu").device == torch.device("cpu")


def test_the_offline_loop_takes_autocast_under_the_online_name():
    assert FitConfig().autocast == "off"
    assert all(FitConfig.preset(p).autocast == "off" for p in ("smoke", "cpu", "paper"))
    assert resolve_execution(FitConfig(autocast="bf16", device="cpu")).autocast == "bf16"
    with pytest.raises(ConfigError, match="fit.autocast must be one of"):
        FitConfig(autocast="fp16")


def _smoke_task(out: Path) -> TaskRunConfig:
    return resolve(TaskRunConfig, {
        "task": "reach-xy", "preset": "smoke", "seed": 3, "seed_dataset": None,
        "out": str(out), "model": {"type": "tdmpc2", "batch_size": 8},
        "train": short(dict(steps=60, seed_steps=40, eval_interval=60, eval_episodes=1,
                            checkpoint_interval=60, buffer_capacity=2_000, device="auto")),
    })  # fmt: skip


def test_a_run_resolves_its_device_once_and_hands_it_down(tmp_path, monkeypatch):
    """One resolution per run (before: the config's device was resolved at every place that
    needed it); the model is built on a torch.device, the trainer and the evaluator get the
    run's `Execution`."""
    import ccfit.settings
    import ccfit.train.run as run
    from ccfit.train import train_single

    calls, models, trainers = [], [], []
    resolve_device = ccfit.settings.resolve_device
    monkeypatch.setattr(ccfit.settings, "resolve_device",
                        lambda name: calls.append(name) or resolve_device(name))  # fmt: skip
    make_model = run.make_model
    monkeypatch.setattr(run, "make_model",
                        lambda cfg, device, **kw: models.append(device) or make_model(
                            cfg, device, **kw))  # fmt: skip

    class SpyTrainer(run.Trainer):
        def __init__(self, **kwargs) -> None:
            super().__init__(**kwargs)
            trainers.append(kwargs["execution"])

    monkeypatch.setattr(run, "Trainer", SpyTrainer)
    train_single(_smoke_task(tmp_path / "run"), progress=False)
    assert calls == ["auto"]
    assert models and all(isinstance(d, torch.device) for d in models)
    (execution,) = trainers
    assert isinstance(execution, Execution) and execution.device == models[0]
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["resolved_device"] == str(execution.device)
    assert saved["resolved_autocast"] == execution.autocast


def test_a_track_resolves_its_execution_once(monkeypatch):
    import ccfit.settings
    from ccfit.curriculum import Curriculum, OnlineTrack

    calls = []
    resolve_device = ccfit.settings.resolve_device
    monkeypatch.setattr(ccfit.settings, "resolve_device",
                        lambda name: calls.append(name) or resolve_device(name))  # fmt: skip
    cfg = resolve(CurriculumConfig, {"suite": "Reach", "preset": "smoke", "seed_dataset": None})
    track = OnlineTrack(cfg)
    track.reference_key()
    track.resolved_config(record_dataset=False)
    runner = Curriculum(cfg, "runs/x", None)
    assert track.execution is track.execution and runner.device == track.execution.device
    assert len(calls) == 2  # one per track: `track`, and the runner's own


def test_validation_reads_no_encoder_file_and_the_run_start_refuses_it(tmp_path, capsys):
    """A config naming an encoder file that is not there constructs (validation does no I/O);
    the run's start reads it and refuses it in one line, exit 2, leaving no run directory."""
    from ccfit.cli import main
    from ccfit.curriculum import OnlineTrack

    missing = tmp_path / "nope.safetensors"
    cfg = resolve(CurriculumConfig, {"suite": "Reach", "preset": "smoke", "obs": "pixels",
                                     "encoder": f"frozen:{missing}"})  # fmt: skip
    assert cfg.encoder_path == str(missing)
    with pytest.raises(ConfigError, match="encoder checkpoint not found"):
        OnlineTrack(cfg)
    with pytest.raises(ConfigError, match="encoder checkpoint not found"):
        with_encoder(cfg)
    (tmp_path / "bad.safetensors").write_bytes(b"not an encoder")
    for command in ("run", "train"):
        where = ["--suite", "Reach"] if command == "run" else ["--task", "reach-xy"]
        code = main([command, *where, "--preset", "smoke", "--obs", "pixels",
                     "--encoder", f"frozen:{tmp_path / 'bad.safetensors'}",
                     "--out", str(tmp_path / command), "--seed_dataset", "null"])  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert "bad.safetensors" in err and "Traceback" not in err
        assert not (tmp_path / command).exists()


def test_obs_and_image_size_are_the_runs_and_the_models_copy_is_derived(tmp_path):
    """The model's config holds the run's obs and image size (recorded in config.json as
    before, so runs keep their identity) but never as an input of its own: one given there
    is dropped, and an old config.json holding it reads back to the same config."""
    cfg = resolve(CurriculumConfig, {"suite": "Reach", "preset": "smoke", "obs": "pixels",
                                     "image_size": 48,
                                     "model": {"obs_mode": "state", "image_size": 64}})  # fmt: skip
    assert (cfg.model.obs_mode, cfg.model.image_size) == ("pixels", 48)
    assert cfg.to_dict()["model"]["obs_mode"] == "pixels"
    assert cfg.to_dict()["model"]["image_size"] == 48
    direct = CurriculumConfig(suite="Reach", obs="pixels", image_size=48)
    assert (direct.model.obs_mode, direct.model.image_size) == ("pixels", 48)
    (tmp_path / "config.json").write_text(json.dumps(cfg.to_dict()))
    assert saved_config(CurriculumConfig, tmp_path) == cfg


def test_a_published_runs_config_reads_back_to_its_identity():
    """`ccfit run --config_path <a published run's config.json>` makes the same run: its
    resolved config has the published one's identity, but for what 'auto' finds on this
    machine: the seed dataset, and the hot paths `--train.compile=auto` picks by today's rule
    (a run resumed in its directory keeps those it began with: `compile_as_begun`)."""
    from ccfit.curriculum import OnlineTrack

    saved = json.loads(PUBLISHED.read_text())
    cfg = parse_cli(CurriculumConfig, ["--config_path", str(PUBLISHED)])
    new = OnlineTrack(cfg).resolved_config(record_dataset=False)
    a, b = flatten(identity(saved)), flatten(identity(new))
    differ = {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)}
    assert differ <= {"resolved_seed_dataset", "resolved_compile"}, differ
    assert new["model"]["obs_mode"] == saved["model"]["obs_mode"] == saved["obs"]
    assert new["model"]["image_size"] == saved["model"]["image_size"] == saved["image_size"]


def test_pretraining_takes_the_device_and_threads_under_the_same_names():
    import argparse

    from ccfit.pretrain import add_pretrain_parser, config_from_args

    parser = argparse.ArgumentParser()
    add_pretrain_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["pretrain-encoder", "--preset", "smoke", "--device", "cuda:1",
                              "--torch-threads", "2"])  # fmt: skip
    config = config_from_args(args)
    assert (config.device, config.torch_threads) == ("cuda:1", 2)
    # one thread unless told otherwise, as training (`--train.torch_threads`)
    assert config_from_args(parser.parse_args(["pretrain-encoder"])).torch_threads == 1
    execution = resolve_execution(PretrainConfig(device="cpu", torch_threads=2,
                                                 model_preset="smoke"))  # fmt: skip
    assert execution == Execution(torch.device("cpu"), torch_threads=2)


def test_a_run_record_reads_back_what_it_left_out_at_its_legacy_value(tmp_path):
    """A setting newer than a run is missing from its config.json, and the run ran as its
    legacy value says: reading the record back gives that value, not today's preset default
    (`train.end_eval_episodes`: none before, 40 at `cpu` now), and only for settings the
    section's type has (DreamerV3's cloning weight, not TD-MPC2's). A config a user wrote, with
    no run's records in it, takes the preset's default."""
    fresh = resolve(CurriculumConfig, {"suite": "Reach", "preset": "cpu"})
    assert fresh.train.end_eval_episodes == 40
    for model, legacy_model_field in (("tdmpc2", None), ("dreamerv3", "demo_bc_coef")):
        cfg = resolve(CurriculumConfig, {"suite": "Reach", "preset": "cpu",
                                         "model": {"type": model}})  # fmt: skip
        record = {**cfg.to_dict(), "resolved_device": "cpu"}
        del record["train"]["end_eval_episodes"]
        if legacy_model_field:
            del record["model"][legacy_model_field]
        (tmp_path / "config.json").write_text(json.dumps(record))
        back = saved_config(CurriculumConfig, tmp_path)
        assert back.train.end_eval_episodes is None
        if legacy_model_field:
            assert getattr(back.model, legacy_model_field) == 0.0
        del record["resolved_device"]  # the same settings, as a user would write them
        (tmp_path / "config.json").write_text(json.dumps(record))
        assert saved_config(CurriculumConfig, tmp_path).train.end_eval_episodes == 40
