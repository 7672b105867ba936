"""`ccdata generate / verify / push` from the command line on a tiny real dataset, and the
explore notebook executed on it."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ccdata.cli import main

NOTEBOOK = Path(__file__).parent.parent / "notebooks" / "explore_dataset.ipynb"


@pytest.fixture(scope="module")
def tiny_reach(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds") / "Reach"
    # One worker: spawning rollout processes costs more than these 4 short episodes (8 s against
    # 11 s with the default 2 on 2 cores); test_record checks that workers change nothing.
    code = main(["generate", "--suite", "Reach", "--episodes", "1", "--explore-episodes", "0",
                 "--image-size", "32", "--root", str(root), "--workers", "1"])  # fmt: skip
    assert code == 0
    return root


def test_generate_prints_summary_and_writes_card(tiny_reach, capsys):
    # Re-running the same command finds every episode present: nothing new, same dataset.
    assert main(["generate", "--suite", "Reach", "--episodes", "1", "--explore-episodes", "0",
                 "--image-size", "32", "--root", str(tiny_reach)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "reach-xyz" in out and "oracle" in out
    assert "4 episodes" in out and "0 new episodes" in out
    card = (tiny_reach / "README.md").read_text()
    assert card.startswith("---\nlicense: mit") and "composition_matrix" in card
    # The card is this dataset's: 32 px, one oracle episode per task, no exploration.
    assert "square 32 px" in card and "Per task: 1 episodes of the scripted `oracle`" in card
    assert "4 episodes," in card and "| `reach-xyz` | oracle | 1 |" in card


def test_generate_refuses_other_settings(tiny_reach, capsys):
    code = main(["generate", "--suite", "Reach", "--episodes", "1", "--explore-episodes", "0",
                 "--image-size", "48", "--root", str(tiny_reach)])  # fmt: skip
    assert code == 2
    assert "image_size" in capsys.readouterr().err


def test_verify_ok_then_finds_a_missing_video(tiny_reach, tmp_path, capsys):
    assert main(["verify", "--root", str(tiny_reach)]) == 0
    assert "OK" in capsys.readouterr().out
    broken = tmp_path / "broken"
    shutil.copytree(tiny_reach, broken)
    next((broken / "videos").rglob("*.mp4")).unlink()
    assert main(["verify", "--root", str(broken)]) == 1
    assert "problem" in capsys.readouterr().out


def test_push_to_loopback_hub_and_errors(tiny_reach, hub_server, monkeypatch, capsys):
    monkeypatch.setenv("HF_TOKEN", hub_server.token("write"))
    args = ["push", "--suite", "Reach", "--root", str(tiny_reach), "--repo-id", "org/reach-tiny"]
    assert main([*args, "--endpoint", hub_server.url]) == 0
    assert "pushed" in capsys.readouterr().out
    assert ("dataset", "org/reach-tiny") in hub_server.state.repos
    assert main([*args, "--endpoint", "http://127.0.0.1:9"]) == 2
    assert "cannot reach" in capsys.readouterr().err
    bad = ["push", "--suite", "Reach", "--root", str(tiny_reach), "--repo-id", "no slash"]
    assert main([*bad, "--endpoint", hub_server.url]) == 2
    monkeypatch.setenv("HF_TOKEN", "hf_wrong")
    assert main([*args, "--endpoint", hub_server.url]) == 2
    err = capsys.readouterr().err
    assert "hf_wrong" not in err and err.count("\n") == 2


def test_the_projects_readers_print_no_torchcodec_traceback(tiny_reach, caplog):
    """Where FFmpeg's shared libraries are absent, LeRobot logs a page of torchcodec traceback
    when it picks a video backend (opening a LeRobotDataset) before it falls back to PyAV;
    ccdata's and ccfit's readers print none."""
    from lerobot.utils.import_utils import get_safe_default_video_backend

    # Another test of this process may have quietened LeRobot (quiet_libraries).
    caplog.set_level(logging.WARNING, logger="lerobot.utils.import_utils")
    if get_safe_default_video_backend() != "pyav" or "torchcodec" not in caplog.text:
        pytest.skip(
            "torchcodec loads here (FFmpeg's shared libraries are present): LeRobot "
            "prints no traceback to hide"
        )

    def stderr_of(code: str) -> str:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=300)  # fmt: skip
        assert done.returncode == 0, done.stderr
        return done.stderr

    root = str(tiny_reach)
    ours = stderr_of(
        "from ccdata.cli import main\n"
        "from ccfit.data import load_episodes\n"
        "from ccfit.pretrain import PretrainConfig\n"
        "from ccfit.pretrain.data import load_frames\n"
        f"root = {root!r}\n"
        "assert len(load_episodes(root)) == 4\n"
        "config = PretrainConfig.preset('smoke', suites='Reach', image_size=32,\n"
        "                               dataset_roots={'Reach': root})\n"
        "assert len(load_frames(config)[0].episodes) == 4\n"
        "assert main(['verify', '--root', root]) == 0\n"
        "assert main(['card', '--root', root, '--out', root + '.card.md']) == 0\n"
    )
    assert "torchcodec" not in ours, ours


@pytest.mark.integration
def test_explore_notebook_runs_on_the_dataset(tiny_reach):
    nbformat = pytest.importorskip("nbformat")
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOK, as_version=4)
    env = {"CCDATA_SUITE": "Reach", "CCDATA_ROOT": str(tiny_reach)}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        NotebookClient(nb, timeout=300, kernel_name="python3").execute()
    finally:
        for k, v in old.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs), "no figure rendered"
    # Without FFmpeg's shared libraries LeRobot logs a page of torchcodec traceback here.
    stderr = "".join(o.get("text", "") for o in outputs if o.get("name") == "stderr")
    assert "torchcodec" not in stderr, stderr


def test_ccfit_reads_a_pushed_dataset_by_repo_id_from_the_endpoint(
    tiny_reach, hub_server, monkeypatch, tmp_path
):
    from ccdata.hub import push_dataset
    from ccfit import data
    from ccfit.replay import ReplayBuffer
    from ccfit.replay_prefill import seed_buffer

    push_dataset(tiny_reach, "org/reach-seed", endpoint=hub_server.url,
                 token=hub_server.token("write"))  # fmt: skip
    monkeypatch.setattr("lerobot.utils.constants.HF_LEROBOT_HOME", tmp_path / "empty-home")
    monkeypatch.setattr("lerobot.utils.constants.HF_LEROBOT_HUB_CACHE", tmp_path / "hub-cache")
    episodes = data.load_episodes("org/reach-seed", task="reach-xz", endpoint=hub_server.url)
    local = data.load_episodes(tiny_reach, task="reach-xz")
    assert len(episodes) == len(local) == 1
    np.testing.assert_array_equal(episodes[0]["action"], local[0]["action"])
    buffer = ReplayBuffer(1000)
    added = seed_buffer(buffer, "org/reach-seed", "reach-xz", "state",
                        endpoint=hub_server.url)  # fmt: skip
    assert sum(added.values()) == 1 and buffer.num_episodes == 1
    with pytest.raises(ValueError, match="cannot read LeRobot dataset 'org/missing'"):
        data.load_episodes("org/missing", endpoint=hub_server.url)
