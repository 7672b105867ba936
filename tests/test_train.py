"""The online loop: replay sampling, observation path, LeRobot reader, training, resume, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ccfit.config import RunConfig, TrainConfig, tdmpc2_preset
from ccfit.obs import obs_to_tensors, stack_cameras
from ccfit.replay import ReplayBuffer

H = 3


# ================================================================================ replay


def _episode(ep_id: int, steps: int, terminated: bool) -> dict:
    """State column 0 = episode id, column 1 = time step; action likewise."""
    t = np.arange(steps + 1, dtype=np.float32)
    state = np.zeros((steps + 1, 39), np.float32)
    state[:, 0], state[:, 1] = ep_id, t
    action = np.zeros((steps, 4), np.float32)
    action[:, 0], action[:, 1] = ep_id, t[:-1]
    term = np.zeros(steps, np.float32)
    term[-1] = float(terminated)
    return dict(obs={"state": state}, action=action, reward=-t[:-1] / 100, terminated=term)


def _filled(seed: int = 0, capacity: int = 10_000) -> ReplayBuffer:
    buf = ReplayBuffer(capacity, seed=seed)
    for i, (steps, term) in enumerate([(20, False), (7, True), (2, False), (H, True), (50, True)]):
        buf.add_episode(**_episode(i, steps, term), task=i % 2)
    return buf


def test_replay_samples_stay_in_one_episode_and_keep_terminals():
    buf = _filled()
    b = buf.sample(4096, H)
    assert b.obs["state"].shape == (H + 1, 4096, 39)
    assert b.action.shape == (H, 4096, 4) and b.reward.shape == (H, 4096, 1)
    ep, t = b.obs["state"][..., 0], b.obs["state"][..., 1]
    assert (ep == ep[0]).all(), "a subsequence crossed an episode boundary"
    assert (t[1:] - t[:-1] == 1).all()
    assert (b.action[..., 0] == ep[:-1]).all() and (b.action[..., 1] == t[:-1]).all()
    assert torch.equal(b.reward[..., 0], -t[:-1] / 100)
    assert torch.equal(b.task, (ep[0].long() % 2))
    lengths = {0: 20, 1: 7, 2: 2, 3: H, 4: 50}
    terminal = {1, 3, 4}
    last = torch.tensor([lengths[int(e)] - 1 for e in ep[0]])
    expected = ((t[:-1] == last) & torch.tensor([int(e) in terminal for e in ep[0]])).float()
    assert torch.equal(b.terminated[..., 0], expected)
    assert b.terminated.sum() > 0, "terminal transitions must be sampled"
    assert not (ep == 2).any(), "an episode shorter than H has no valid start"
    # Uniform over the valid starts: every start appears, none far from the mean count.
    starts = {(int(e), int(s)) for e, s in zip(ep[0], t[0], strict=True)}
    n_valid = sum(max(0, n - H + 1) for n in lengths.values())
    assert len(starts) == n_valid == buf.num_starts(H)
    counts = np.unique(ep[0] * 1000 + t[0], return_counts=True)[1]
    assert counts.min() > 0.4 * 4096 / n_valid and counts.max() < 1.8 * 4096 / n_valid


def test_replay_same_seed_same_batches_and_state_roundtrip():
    a, b, c = _filled(seed=1), _filled(seed=1), _filled(seed=2)
    ba, bb, bc = a.sample(64, H), b.sample(64, H), c.sample(64, H)
    assert torch.equal(ba.obs["state"], bb.obs["state"])
    assert not torch.equal(ba.obs["state"], bc.obs["state"])
    restored = ReplayBuffer(10_000, seed=99)
    restored.load_state_dict(a.state_dict())
    assert torch.equal(restored.sample(64, H).obs["state"], a.sample(64, H).obs["state"])


def test_replay_capacity_drops_oldest_whole_episodes():
    buf = ReplayBuffer(100, seed=0)
    for i in range(5):
        buf.add_episode(**_episode(i, 29, False))  # 30 rows each
    b = buf.sample(2000, H)
    assert set(b.obs["state"][0, :, 0].long().tolist()) == {2, 3, 4}
    assert buf.num_episodes == 3 and buf.num_transitions == 87
    with pytest.raises(ValueError, match="before the last transition"):
        bad = _episode(9, 5, False)
        bad["terminated"][2] = 1
        buf.add_episode(**bad)


# =========================================================================== observations


def test_obs_path_stacks_cameras_in_order_for_live_frames():
    from ccdata import make_env

    env = make_env("reach-xy", seed=0, image_size=32)
    obs, _ = env.reset(seed=0)
    x = obs_to_tensors(obs, "pixels")
    env.close()
    assert x["pixels"].shape == (9, 32, 32) and x["pixels"].dtype == torch.uint8
    for i, cam in enumerate(("topview", "frontview", "gripperPOV")):
        chw = torch.from_numpy(obs[cam]).permute(2, 0, 1)
        assert torch.equal(x["pixels"][3 * i : 3 * i + 3], chw)
    assert torch.equal(x["proprio"], torch.from_numpy(obs["proprio"]))
    assert set(obs_to_tensors(obs, "state")) == {"state"}
    seq = {c: np.stack([obs[c]] * 2) for c in ("topview", "frontview", "gripperPOV")}
    assert np.array_equal(stack_cameras(seq)[1], x["pixels"].numpy())
    with pytest.raises(ValueError, match="valid: state, pixels"):
        obs_to_tensors(obs, "rgb")


# ======================================================================== LeRobot reader


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """A finalized LeRobot v3 dataset in ccdata's schema from real rollouts (32 px cameras):
    an oracle reach-xy episode that ends in success, and 12 random steps of reach-xyz."""
    from lerobot.configs import RGBEncoderConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from ccdata import make_env
    from ccdata.dataset_format import VIDEO_ENCODER, ccdata_metadata, features
    from ccdata.policies import make_policy
    from ccdata.record import GenerateConfig

    root = tmp_path_factory.mktemp("ds") / "Reach"
    size = 32
    ds = LeRobotDataset.create(
        "ccdata/Reach", fps=40, features=features(size), root=root, use_videos=True,
        rgb_encoder=RGBEncoderConfig(**json.loads(json.dumps(VIDEO_ENCODER))),
    )  # fmt: skip
    meta = ccdata_metadata(GenerateConfig(suite="Reach", root=root))
    written = []
    # (task id, task_id_index, policy, policy_index, episode seed, step limit)
    plan = [("reach-xy", 0, "oracle", 0, 101, 250), ("reach-xyz", 3, "random", 2, 102, 12)]
    for task_id, task_i, policy_name, pol_i, seed, limit in plan:
        env = make_env(task_id, image_size=size)
        policy = make_policy(policy_name, task_id, seed=0)
        policy.reset()
        obs, _ = env.reset(seed=seed)
        rec = {"state": [], "img": []}
        for t in range(limit):
            action = np.asarray(policy.act(obs), np.float32)
            nxt, reward, terminated, truncated, info = env.step(action)
            last = terminated or truncated or t + 1 == limit
            imgs = [obs[c] for c in ("topview", "frontview", "gripperPOV")]
            rec["state"].append(obs["state"])
            rec["img"].append(imgs)
            ds.add_frame({
                "observation.images.topview": imgs[0],
                "observation.images.frontview": imgs[1],
                "observation.images.gripperPOV": imgs[2],
                "observation.state": obs["proprio"],
                "observation.environment_state": obs["state"],
                "action": action,
                "next.reward": np.array([reward], np.float32),
                "next.done": np.array([last]),
                "next.success": np.array([bool(info["success"])]),
                "task_id_index": np.array([task_i]),
                "policy_index": np.array([pol_i]),
                "episode_seed": np.array([seed]),
                # no final-observation frame: the layout of format-1 datasets
                "is_final_observation": np.array([False]),
                "task": meta["tasks"][task_i]["instruction"],
            })  # fmt: skip
            obs = nxt
            if last:
                break
        rec["final_state"], rec["success"] = obs["state"], bool(info["success"])
        env.close()
        ds.save_episode()
        written.append(rec)
    ds.finalize()
    (root / "meta" / "ccdata.json").write_text(json.dumps(meta))
    assert written[0]["success"] and not written[1]["success"]
    return root, written


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def test_load_episodes_matches_written_frames(tiny_dataset):
    from ccfit.data import episode_to_replay, load_episodes

    root, written = tiny_dataset
    eps = load_episodes(root)
    assert [e["episode_index"] for e in eps] == [0, 1]
    assert [e["task_id"] for e in eps] == ["reach-xy", "reach-xyz"]
    assert [e["policy"] for e in eps] == ["oracle", "random"]
    for ep, rec in zip(eps, written, strict=True):
        assert np.array_equal(ep["observation.environment_state"], np.stack(rec["state"]))
        for c, cam in enumerate(("topview", "frontview", "gripperPOV")):
            decoded = ep[f"observation.images.{cam}"]
            truth = np.stack([imgs[c] for imgs in rec["img"]])
            assert decoded.shape == truth.shape and decoded.dtype == np.uint8
            assert min(_psnr(d, w) for d, w in zip(decoded, truth, strict=True)) >= 40.0
    only = load_episodes(root, task="reach-xyz", policy="random", images=False)
    assert [e["episode_index"] for e in only] == [1]
    assert "observation.images.topview" not in only[0]
    with pytest.raises(ValueError, match="valid: reach-xy"):
        load_episodes(root, task="pick-cube")
    with pytest.raises(ValueError, match="match"):
        load_episodes(root, task="reach-xy", policy="random")

    # Into replay: T frames -> T observations and T-1 transitions, pixels via ccfit.obs.
    steps = len(written[1]["state"])
    r = episode_to_replay(eps[1], "pixels")
    assert r["obs"]["pixels"].shape == (steps, 9, 32, 32) and r["action"].shape == (steps - 1, 4)
    assert np.array_equal(r["obs"]["pixels"][:, 3:6], np.moveaxis(
        eps[1]["observation.images.frontview"], -1, 1))  # fmt: skip
    buf = ReplayBuffer(1000)
    buf.add_episode(**r)
    assert buf.num_transitions == steps - 1


# ============================================================================== training


def _run_config(steps=120, checkpoint_interval=60) -> RunConfig:
    train = TrainConfig(
        steps=steps, seed_steps=40, batch_size=8, eval_interval=60, eval_episodes=1,
        checkpoint_interval=checkpoint_interval, buffer_capacity=2_000, seed=3, device="cpu",
    )  # fmt: skip
    return RunConfig("reach-xy", "tdmpc2", tdmpc2_preset("smoke", "state"), train)


def _params(out: Path) -> dict[str, torch.Tensor]:
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    flat = {f"model.{k}": v for k, v in state["model"].items()}
    flat.update({f"heads.{k}": v for k, v in state["heads"].items()})
    return flat


def test_resume_after_interruption_matches_uninterrupted_run(tmp_path, monkeypatch):
    from ccfit.models.tdmpc2 import TDMPC2
    from ccfit.train import train_task

    full = tmp_path / "full"
    train_task(_run_config(), full, progress=False)

    # Kill the second run mid-way between its checkpoint (step 60) and the end.
    original = TDMPC2.loss
    calls = {"n": 0}

    def dying_loss(self, batch, heads):
        calls["n"] += 1
        if calls["n"] == 45:  # updates start at step 40: this is step ~85
            raise KeyboardInterrupt
        return original(self, batch, heads)

    broken = tmp_path / "broken"
    monkeypatch.setattr(TDMPC2, "loss", dying_loss)
    with pytest.raises(KeyboardInterrupt):
        train_task(_run_config(), broken, progress=False)
    monkeypatch.setattr(TDMPC2, "loss", original)
    assert torch.load(broken / "checkpoint.pt", weights_only=False)["task_step"] == 60
    train_task(_run_config(), broken, progress=False)

    a, b = _params(full), _params(broken)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed run diverged"
    rec_a = (full / "metrics.jsonl").read_text().splitlines()
    rec_b = (broken / "metrics.jsonl").read_text().splitlines()
    assert rec_a == rec_b and [json.loads(x)["task_step"] for x in rec_a] == [0, 60, 120]
    # A different config must not silently reuse the directory.
    with pytest.raises(ValueError, match="different config"):
        train_task(_run_config(steps=180), broken, progress=False)


def test_cli_smoke_run_writes_config_metrics_checkpoint(tmp_path):
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "ccfit.cli",
        "train",
        "--task",
        "reach-xy",
        "--model",
        "tdmpc2",
        "--obs",
        "state",
        "--preset",
        "smoke",
        "--out",
        str(out),
        "--quiet",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["task"] == "reach-xy" and cfg["model"] == "tdmpc2"
    assert cfg["train"]["horizon"] == cfg["model_config"]["horizon"] == 3
    assert cfg["model_config"]["obs_mode"] == cfg["train"]["obs"] == "state"
    records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    steps = TrainConfig.preset("smoke").steps
    interval = TrainConfig.preset("smoke").eval_interval
    assert [r["global_step"] for r in records] == list(range(0, steps + 1, interval))
    from ccdata.scoring import floor_return

    for r in records:
        assert r["task"] == "reach-xy" and 0.0 <= r["success_rate"] <= 1.0
        assert floor_return() - 1e-6 <= r["discounted_return"] <= 0.0
        assert set(r) >= {"task_step", "normalized_return", "discounted_return"}
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ckpt["task_step"] == steps and ckpt["buffer"]["episodes"].shape[0] >= 2
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert "reach-xy step 600" in proc.stdout


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["train", "--task", "reach-nowhere"], "reach-xy"),
        (["train", "--task", "reach-xy", "--model", "dreamer9"], "valid: tdmpc2"),
        (["train", "--task", "reach-xy", "--preset", "huge"], "valid: smoke, cpu, paper"),
        (["train", "--task", "reach-xy", "--obs", "rgb"], "state"),
        (["train", "--task", "reach-xy", "--seed-dataset", "/no/such/dir"], "cannot read"),
        (["train"], "--task"),
        (["fly"], "invalid choice"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(argv, needle, capsys, tmp_path):
    from ccfit.cli import main

    try:
        code = main([*argv, "--out", str(tmp_path / "x")] if argv[0] == "train" else argv)
    except SystemExit as e:  # argparse errors
        code = e.code
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err
    assert not (tmp_path / "x").exists(), "bad input must not leave a run directory"


def test_seed_buffer_preloads_the_tasks_episodes(tiny_dataset):
    from ccfit.data import final_observation, load_episodes
    from ccfit.train import seed_buffer

    root, written = tiny_dataset
    steps = len(written[0]["state"])
    buf = ReplayBuffer(1000)
    assert seed_buffer(buf, root, "reach-xy", "state") == 1
    # The success ended the episode: its final observation is replayed, the terminal kept.
    assert buf.num_episodes == 1 and buf.num_transitions == steps
    b = buf.sample(256, 1)
    final = b.terminated[0, :, 0] == 1
    assert final.any()
    assert torch.equal(b.obs["state"][1, final][0], torch.from_numpy(written[0]["final_state"]))
    ep = load_episodes(root, task="reach-xy", images=False)[0]
    ep["observation.environment_state"][2, 0] += 0.01
    with pytest.raises(ValueError, match="departs from the recorded states at step 2"):
        final_observation(ep, "reach-xy")
    with pytest.raises(ValueError, match="32 px but the run uses 64"):
        seed_buffer(ReplayBuffer(1000), root, "reach-xyz", "pixels", image_size=64)


class _CountingMethod:
    """A continual method that only counts the hooks the loop calls."""

    def __init__(self) -> None:
        self.penalties = self.after_steps = 0

    def penalty(self, backbone, backbone_loss):
        self.penalties += 1
        return 0.0 * sum(p.sum() for p in backbone.parameters())

    def after_step(self, backbone) -> None:
        self.after_steps += 1


def test_trainer_calls_continual_hooks_once_per_update():
    from ccdata import make_env
    from ccfit.models.tdmpc2 import TDMPC2
    from ccfit.train import Trainer

    torch.manual_seed(0)
    cfg = TrainConfig(steps=50, seed_steps=20, updates_per_step=2, batch_size=4,
                      eval_interval=50, eval_episodes=1, checkpoint_interval=50,
                      buffer_capacity=1000, device="cpu")  # fmt: skip
    model = TDMPC2(tdmpc2_preset("smoke", "state"), device="cpu")
    env = make_env("reach-xy", render=False)
    method = _CountingMethod()
    buffer = ReplayBuffer(1000)
    buffer.add_episode(**_episode(0, 30, False))  # sampleable from the first update step on
    before = [p.detach().clone() for p in model.backbone.parameters()]
    trainer = Trainer(env=env, model=model, heads=model.new_heads(), buffer=buffer,
                      config=cfg, task_id="reach-xy", method=method, progress=False)  # fmt: skip
    last = trainer.run()
    env.close()
    assert last["task_step"] == 50 and [r["task_step"] for r in trainer.evals] == [0, 50]
    assert trainer.updates == (50 - 20) * 2
    assert method.penalties == method.after_steps == trainer.updates
    assert buffer.num_transitions == 30 + 50  # the episode in progress is stored at the end
    after = list(model.backbone.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, after, strict=True))
