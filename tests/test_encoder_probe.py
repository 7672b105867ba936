"""`ccfit probe-encoder`: the ridge scorer on data of known content, and the command end to end
on real renders through a (random) frozen encoder."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ccfit.analysis.encoder_probe import ridge_r2
from ccfit.cli import main

SIZE = 32


def test_ridge_r2_scores_what_the_inputs_hold():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 6))
    y = np.stack([x @ rng.normal(size=6), rng.normal(size=400), np.full(400, 0.3)], axis=1)
    linear, noise, constant = ridge_r2(x, y)
    assert linear > 0.99 and noise < 0.05 and constant is None


@pytest.fixture
def encoder_path(tmp_path):
    from ccfit.models.encoders import build_encoder, save_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config

    cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    torch.manual_seed(0)
    path = tmp_path / "enc.safetensors"
    save_encoder(build_encoder(cfg), cfg, path)
    return path


def test_probe_reports_the_positions_each_task_varies(encoder_path, tmp_path, capsys):
    out = tmp_path / "probe"
    assert main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy,reach-xyz",
                 "--frames", "30", "--out", str(out)]) in (0, None)  # fmt: skip
    result = json.loads((out / "probe.json").read_text())
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
