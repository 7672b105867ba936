"""`ccfit probe-encoder`: the ridge scorer on data of known content, and the command end to end
on real renders through a (random) frozen encoder."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch

from ccfit.analysis.encoder_probe import probe_rows, ridge_r2
from ccfit.cli import main

SIZE = 32


def test_ridge_r2_scores_what_the_inputs_hold():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 6))
    y = np.stack([x @ rng.normal(size=6), rng.normal(size=400), np.full(400, 0.3)], axis=1)
    linear, noise, constant = ridge_r2(x, y)
    assert linear > 0.99 and noise < 0.05 and constant is None


def test_probe_rows_score_each_varying_position_and_drop_the_rest():
    """A 'latent' that holds the hand (plus noise) and nothing of the goal: the hand scores
    near 1, the goal near 0 or below, a coordinate that never varies and an absent object are
    left out, and the pixels column is scored from its own input."""
    rng = np.random.default_rng(1)
    state = np.zeros((300, 39))
    state[:, 0:3] = rng.uniform(-0.3, 0.3, (300, 3))  # hand
    state[:, 36:38] = rng.uniform(-0.2, 0.2, (300, 2))  # goal x, y; its z stays 0
    latent = np.concatenate([state[:, 0:3], rng.normal(size=(300, 5))], axis=1)
    latent[:, :3] += 0.01 * rng.normal(size=(300, 3))
    rows = probe_rows("t", {"latent": latent, "pixels": state[:, 36:38].copy(), "state": state})
    by = {r["position"]: r for r in rows}
    assert set(by) == {"hand", "goal"} and by["goal"]["axes"] == "xy"
    assert min(by["hand"]["latent_r2"]) > 0.99 and max(by["goal"]["latent_r2"]) < 0.1
    # The pixel probe's penalty (10x, for thousands of pooled inputs) shrinks two exact ones.
    assert min(by["goal"]["pixels_r2"]) > 0.85


@pytest.fixture
def encoder_path(tmp_path):
    from ccfit.models.encoders import build_encoder, save_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config

    cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    torch.manual_seed(0)
    path = tmp_path / "enc.safetensors"
    save_encoder(build_encoder(cfg), cfg, path)
    return path


@pytest.mark.integration
def test_probe_reports_the_positions_each_task_varies(encoder_path, tmp_path, capsys):
    out = tmp_path / "probe"
    assert main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy,reach-xyz",
                 "--frames", "30", "--out", str(out)]) == 0  # fmt: skip
    result = json.loads((out / "probe.json").read_text())
    # the encoder by name and content: no path of the machine that probed it
    assert result["encoder"] == "enc.safetensors" and str(tmp_path) not in json.dumps(result)
    assert result["encoder_sha256"] == hashlib.sha256(encoder_path.read_bytes()).hexdigest()
    rows = {(r["task"], r["position"]): r for r in result["rows"]}
    # Reach has no object; reach-xy's goal moves in x and y only, reach-xyz's in all three.
    assert set(rows) == {(t, p) for t in ("reach-xy", "reach-xyz") for p in ("hand", "goal")}
    assert rows["reach-xy", "goal"]["axes"] == "xy" and rows["reach-xyz", "goal"]["axes"] == "xyz"
    assert rows["reach-xy", "hand"]["axes"] == "xyz"
    for r in rows.values():
        assert len(r["latent_r2"]) == len(r["pixels_r2"]) == len(r["axes"])
    table = (out / "probe.md").read_text()
    assert table in capsys.readouterr().out and table.count("\n") == 2 + len(rows)


@pytest.mark.parametrize("args, message", [
    (["--tasks", "reach-qq"], "unknown task 'reach-qq'"),
    (["--tasks", "reach-xy", "--frames", "5"], "--frames must be at least 10"),
])  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(args, message, encoder_path, tmp_path, capsys):
    code = main(["probe-encoder", str(encoder_path), *args, "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    code = main(["probe-encoder", str(tmp_path / "none.safetensors"), "--tasks", "reach-xy",
                 "--out", str(tmp_path / "p")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "encoder checkpoint not found" in err, err
