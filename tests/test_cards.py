"""Dataset cards: a generated dataset's card (its README.md) states the settings it was generated
with and what was measured on it; cards/<Suite>.md is the default settings' card."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

import ccdata
from ccdata.cards import render_card
from ccdata.cli import main
from ccdata.dataset_format import episode_table, read_ccdata_metadata
from ccdata.record import GenerateConfig, generate

SETTINGS = dict(suite="Reach", episodes=2, explore_episodes=1, image_size=32, max_steps=10, seed=3)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("cards") / "Reach"
    return generate(GenerateConfig(**SETTINGS, root=root), progress=False)


def header(card: str) -> dict:
    return yaml.safe_load(card.split("---")[1])


def test_a_32px_dataset_card_states_its_settings_and_real_counts(small):
    root, summary = small
    card = (root / "README.md").read_text()
    head = header(card)["ccdata"]
    assert head["image_size"] == 32 and head["seed"] == 3
    assert head["episodes_per_task"] == {"oracle": 2, "noisy-oracle": 1, "random": 1}
    assert "square 32 px" in card and "`image_size`: 32" in card and "64 px" not in card
    assert "Per task: 2 episodes of the scripted `oracle`" in card
    assert "1 episodes each of `noisy-oracle` and `random`" in card
    assert "cut after at most 10 steps" in card
    assert (
        "ccdata generate --suite Reach --episodes 2 --explore-episodes 1 --image-size 32 "
        "--seed 3 --max-steps 10"
    ) in card
    # The measured table is the dataset's own content, row by row.
    table = episode_table(root)
    meta = read_ccdata_metadata(root)
    ids = [t["id"] for t in meta["tasks"]]
    assert summary["episodes"] == 16 == len(table["episode_index"])
    for t, task_id in enumerate(ids):
        for p, policy in enumerate(meta["policies"]):
            m = (table["task_id_index"] == t) & (table["policy_index"] == p)
            row = (
                f"| `{task_id}` | {policy} | {int(m.sum())} | {int(table['steps'][m].sum())} "
                f"| {table['success'][m].mean():.2f} | {np.mean(table['return'][m]):.2f} |"
            )
            assert row in card, row
    assert f"{summary['episodes']} episodes, {summary['steps']} steps" in card
    videos = sum(p.stat().st_size for p in (root / "videos").rglob("*") if p.is_file())
    assert f"{1000 * videos / summary['frames'] / 1e6:.2f} MB of video" in card
    assert f"lerobot {meta['versions']['lerobot']}" in card
    # Each task's noisy-oracle noise, as calibrated and as recorded in the metadata.
    for task_id in ids:
        noise = ccdata.get_task(task_id).exploration
        assert f"| `{task_id}` | {noise.noise_std} | {noise.random_prob} |" in card
        assert meta["policy_params"]["noisy-oracle"]["per_task"][task_id] == noise.to_dict()


def test_card_command_rerenders_a_datasets_card(small, tmp_path, capsys):
    root, _ = small
    out = tmp_path / "card.md"
    assert main(["card", "--root", str(root), "--out", str(out)]) == 0
    assert out.read_text() == (root / "README.md").read_text()
    assert main(["card"]) == 2
    assert "give --suite" in capsys.readouterr().err
    assert main(["card", "--suite", "Reach", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err == (
        f"ccdata card: error: --out {tmp_path} is a directory: name the card's file\n"
    )
    damaged = shutil.copytree(root, tmp_path / "damaged")
    data = next((damaged / "data").rglob("*.parquet"))
    data.write_bytes(data.read_bytes()[:100])  # the card reads every episode from it
    assert main(["card", "--root", str(damaged)]) == 2
    err = capsys.readouterr().err
    assert f"the dataset at {damaged} is damaged, so its card cannot be written (" in err
    assert err.count("\n") == 1


def test_default_card_states_the_default_settings():
    card = render_card("PnPBoxClose")
    head = header(card)["ccdata"]
    assert head["image_size"] == 64
    assert head["episodes_per_task"] == {"oracle": 50, "noisy-oracle": 25, "random": 25}
    assert "square 64 px" in card and "## Measured on this dataset" not in card
    for task in ccdata.get_suite("PnPBoxClose").tasks:
        noise = task.exploration
        assert f"| `{task.id}` | {noise.noise_std} | {noise.random_prob} |" in card


def test_overridden_noise_is_stated_for_every_task():
    card = render_card(GenerateConfig("Grasp", noise_std=0.2, random_prob=0.0))
    for task_id in ccdata.get_suite("Grasp").task_ids:
        assert f"| `{task_id}` | 0.2 | 0.0 | — |" in card
    assert "noise set for every task by the generating command" in card
    assert "--noise-std 0.2 --random-prob 0.0" in card


def test_settings_is_a_leaf_that_readers_import_instead_of_the_engine():
    import subprocess
    import sys

    code = (
        "import sys, ccdata.settings; engine = ('record', 'journal', 'dataset_format', "
        "'writer', 'cards'); print(sorted(m for m in sys.modules if m.startswith('ccdata.') "
        "and m.split('.')[1] in engine)); import ccdata.cards, ccdata.journal, "
        "ccdata.dataset_format, ccfit.data, ccfit.curriculum, ccfit.pretrain.data; "
        "print(sorted(m for m in ('ccdata.record', 'ccdata.writer') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split("\n")
    assert out[:2] == ["[]", "[]"]
    from ccdata.record import GenerateConfig as Old
    from ccdata.settings import DatasetSettings

    assert (
        issubclass(Old, DatasetSettings)
        and Old("Reach").dataset_root == DatasetSettings("Reach").dataset_root
    )
