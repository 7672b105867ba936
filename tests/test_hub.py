"""Publishing LeRobot v3 datasets to a Hub-compatible endpoint (a real server on loopback)."""

import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from huggingface_hub import constants
from huggingface_hub.repocard import RepoCard

from ccdata.dataset_format import CODEBASE_VERSION
from ccdata.hub import HubError, download_dataset, push_dataset
from ccdata.repo_id import validate_repo_id

REPO_ID = "ccbench-test/tiny"
CAMERA = "observation.images.top"
CARD = "---\nlicense: mit\ntags:\n- LeRobot\n---\n\n# tiny\n\nA two-episode test dataset.\n"

# Every outgoing connection the process opens while `_CONNECTIONS` is a list (audit hooks are
# process-wide and permanent, so the hook is installed once and usually does nothing).
_CONNECTIONS: list | None = None


def _audit(event, args):
    if _CONNECTIONS is not None and event in ("socket.connect", "socket.getaddrinfo"):
        _CONNECTIONS.append((event, args[1] if event == "socket.connect" else args[0]))


sys.addaudithook(_audit)


def _only_loopback(connections, port):
    """The hosts/addresses contacted other than 127.0.0.1:port (empty if none)."""
    bad = []
    for event, target in connections:
        if event == "socket.getaddrinfo" and target not in ("127.0.0.1", b"127.0.0.1"):
            bad.append(target)
        if (
            event == "socket.connect"
            and isinstance(target, tuple)
            and target[:2] != ("127.0.0.1", port)
        ):
            bad.append(target)
    return bad


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """A finalized LeRobot v3 dataset: 2 episodes of 6 and 9 frames, one 32 px video camera."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path_factory.mktemp("local") / "tiny"
    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
        CAMERA: {"dtype": "video", "shape": (32, 32, 3), "names": ["height", "width", "channels"]},
    }
    ds = LeRobotDataset.create(
        REPO_ID, fps=10, features=features, root=root, use_videos=True, video_backend="pyav"
    )
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 255, 32, dtype=np.float32)
    for ep, length in enumerate((6, 9)):
        for t in range(length):
            # Smooth moving gradients: content a lossy codec keeps recognizable frame to frame.
            image = np.stack(
                np.broadcast_arrays(
                    ramp[None, :], ramp[:, None], np.full((32, 32), 40.0 * t + 100 * ep)
                ),
                -1,
            )
            ds.add_frame(
                {
                    "observation.state": rng.standard_normal(4).astype(np.float32),
                    "action": rng.uniform(-1, 1, 4).astype(np.float32),
                    CAMERA: (image % 256).astype(np.uint8),
                    "task": f"task {ep}",
                }
            )
        ds.save_episode()
    ds.finalize()
    (root / "README.md").write_text(CARD)
    return root


@pytest.fixture
def clean_hub_env(monkeypatch, tmp_path):
    """No token, endpoint or offline switch inherited from the machine running the tests."""
    for var in (
        "HF_TOKEN",
        "HUGGING_FACE_HUB_TOKEN",
        "HF_ENDPOINT",
        "HF_HUB_OFFLINE",
        "HF_OIDC_RESOURCE",
    ):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(constants, "HF_TOKEN_PATH", str(tmp_path / "no-token"))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hf-hub-cache"))


def _local_files(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and ".cache" not in p.parts
    }


def _remote(hub, rev="main"):
    repo = hub.state.repos[("dataset", REPO_ID)]
    oid = repo.branches.get(rev) or repo.tags[rev]
    return repo, oid, repo.commits[oid].tree


def _read_all(ds) -> dict[str, np.ndarray]:
    keys = ("observation.state", "action", CAMERA, "timestamp", "episode_index", "frame_index")
    return {k: np.stack([ds[i][k].numpy() for i in range(len(ds))]) for k in keys}


def test_validate_repo_id():
    for ok in ("org/name", "My_Org/data.set-v1", "a/b", "x" * 96 + "/" + "y" * 96):
        assert validate_repo_id(ok) == ok
    bad = {
        "name-only": "ORG/NAME",
        "a/b/c": "ORG/NAME",
        "org/": "1 to 96",
        "org/" + "n" * 97: "1 to 96",
        "org/na me": "letters, digits",
        "org/-name": "start and end",
        "org/name.": "start and end",
        "org/na--me": "'--'",
        "org/na..me": "'..'",
        "org/name.git": ".git",
        "örg/name": "letters",
    }
    for repo_id, words in bad.items():
        with pytest.raises(ValueError, match=words.replace(".", r"\.")) as err:
            validate_repo_id(repo_id)
        assert repr(repo_id) in str(err.value)


def test_push_repush_then_lerobot_loads_from_empty_cache(
    hub_server, tiny_dataset, clean_hub_env, monkeypatch, tmp_path
):
    global _CONNECTIONS
    # Simulate a process that imported huggingface_hub before ccdata.hub, with Xet and telemetry
    # on: the push must still talk only to the endpoint.
    monkeypatch.setattr(constants, "HF_HUB_DISABLE_XET", False)
    monkeypatch.setattr(constants, "HF_HUB_DISABLE_TELEMETRY", False)
    validate_calls = []
    monkeypatch.setattr(RepoCard, "validate", lambda *a, **k: validate_calls.append(a))
    # The token is found the usual way (HF_TOKEN), never passed in.
    monkeypatch.setenv("HF_TOKEN", hub_server.token("write"))
    local = tmp_path / "tiny"
    shutil.copytree(tiny_dataset, local)
    (local / "notes.txt").write_text("scratch file, removed before the third push\n")

    _CONNECTIONS = []
    try:
        url = push_dataset(local, REPO_ID, endpoint=hub_server.url)
        repo, head1, tree = _remote(hub_server)
        assert repo.tags == {CODEBASE_VERSION: head1}
        n_commits = len(repo.commits)
        # Unchanged data: no new commit, the tag stays, nothing is deleted.
        n_requests = len(hub_server.requests)
        assert push_dataset(local, REPO_ID, endpoint=hub_server.url) == url
        assert len(repo.commits) == n_commits and repo.tags == {CODEBASE_VERSION: head1}
        assert not [r for r in hub_server.requests[n_requests:] if r["method"] == "DELETE"]
        # Changed card, removed file: one new commit mirroring the folder, the tag follows it.
        (local / "README.md").write_text(CARD.replace("test dataset", "test dataset, v2"))
        (local / "notes.txt").unlink()
        push_dataset(local, REPO_ID, endpoint=hub_server.url)
        _, head3, tree = _remote(hub_server)
        connections = _CONNECTIONS
    finally:
        _CONNECTIONS = None

    assert url == f"{hub_server.url}/datasets/{REPO_ID}"
    assert head3 != head1 and repo.tags == {CODEBASE_VERSION: head3}
    assert len(repo.commits) == n_commits + 1
    local_files = _local_files(local)
    assert set(tree) == set(local_files) | {".gitattributes"}
    for path, data in local_files.items():
        assert hub_server.state.read(tree[path]) == data, path
    # LFS was used for the binary files (parquet, mp4), inline commits for the JSON/markdown.
    assert tree[f"videos/{CAMERA}/chunk-000/file-000.mp4"].sha256 is not None
    assert tree["meta/info.json"].sha256 is None

    # Only the endpoint was contacted: no Xet storage, no telemetry side requests, no card
    # validation against a hard-coded host.
    assert _only_loopback(connections, hub_server.port) == []
    assert {r["host"] for r in hub_server.requests} == {f"127.0.0.1:{hub_server.port}"}
    assert not [r for r in hub_server.requests if "xet" in r["path"] or "agent" in r["path"]]
    assert validate_calls == []

    # A fresh process with an empty cache reads it through LeRobot, pointed at the endpoint.
    out = tmp_path / "loaded.npz"
    script = textwrap.dedent(f"""
        import json, sys
        seen = []
        sys.addaudithook(lambda e, a: seen.append([e, repr(a[1] if e == "socket.connect"
                         else a[0])]) if e in ("socket.connect", "socket.getaddrinfo") else None)
        import numpy as np
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
        ds = LeRobotDataset({REPO_ID!r}, video_backend="pyav")
        keys = ("observation.state", "action", {CAMERA!r}, "timestamp", "episode_index",
                "frame_index")
        arrays = {{k: np.stack([ds[i][k].numpy() for i in range(len(ds))]) for k in keys}}
        np.savez({str(out)!r}, **arrays)
        print(json.dumps({{"root": str(ds.root), "episodes": ds.num_episodes,
                          "revision": ds.revision, "seen": seen}}))
    """)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGING_FACE"))}
    env.update(
        HF_ENDPOINT=hub_server.url,
        HF_HOME=str(tmp_path / "hf-home"),
        HF_LEROBOT_HOME=str(tmp_path / "lerobot-home"),
        HF_HUB_DISABLE_TELEMETRY="1",
        HF_HUB_DISABLE_XET="1",
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["episodes"] == 2 and report["revision"] == CODEBASE_VERSION
    assert report["root"].startswith(str(tmp_path / "lerobot-home" / "hub"))
    assert report["root"].endswith(head3)
    for event, target in report["seen"]:
        assert "127.0.0.1" in target, (event, target)

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    expected = _read_all(LeRobotDataset(REPO_ID, root=tiny_dataset, video_backend="pyav"))
    loaded = dict(np.load(out))
    assert loaded[CAMERA].shape == (15, 3, 32, 32)
    assert list(loaded["episode_index"]) == [0] * 6 + [1] * 9
    for key, value in expected.items():
        np.testing.assert_array_equal(loaded[key], value, err_msg=key)
    # The frames are the recorded gradients, not just self-consistent: episode 1 is brighter.
    blue = loaded[CAMERA][:, 2].mean(axis=(1, 2))
    assert blue[6] > blue[0] + 0.2


def test_download_dataset_to_root_and_cache(
    hub_server, tiny_dataset, clean_hub_env, monkeypatch, tmp_path
):
    push_dataset(tiny_dataset, REPO_ID, endpoint=hub_server.url, token=hub_server.token("write"))
    got = download_dataset(REPO_ID, endpoint=hub_server.url, root=tmp_path / "copy")
    assert got == tmp_path / "copy"
    assert _local_files(got).items() >= _local_files(tiny_dataset).items()

    import lerobot.utils.constants as lr_constants

    monkeypatch.setattr(lr_constants, "HF_LEROBOT_HUB_CACHE", tmp_path / "cache")
    snap = download_dataset(REPO_ID, endpoint=hub_server.url)
    _, head, _ = _remote(hub_server, CODEBASE_VERSION)
    cache_name = f"datasets--{REPO_ID.replace('/', '--')}"
    assert snap == tmp_path / "cache" / cache_name / "snapshots" / head
    assert _local_files(snap).items() >= _local_files(tiny_dataset).items()

    # Without the tag (a repo pushed by other tools), main is used.
    hub_server.state.repos[("dataset", REPO_ID)].tags.clear()
    again = download_dataset(REPO_ID, endpoint=hub_server.url, root=tmp_path / "untagged")
    assert (again / "meta" / "info.json").read_bytes() == (
        tiny_dataset / "meta" / "info.json"
    ).read_bytes()

    with pytest.raises(HubError, match="not found on") as err:
        download_dataset("ccbench-test/missing", endpoint=hub_server.url, root=tmp_path / "m")
    assert "\n" not in str(err.value)

    # A private dataset is readable with a token only.
    private_id = "ccbench-test/private"
    push_dataset(
        tiny_dataset,
        private_id,
        endpoint=hub_server.url,
        private=True,
        token=hub_server.token("write"),
    )
    assert hub_server.state.repos[("dataset", private_id)].private
    with pytest.raises(HubError, match=r"not found on .* \(or it is private"):
        download_dataset(private_id, endpoint=hub_server.url, root=tmp_path / "p1")
    got = download_dataset(
        private_id, endpoint=hub_server.url, root=tmp_path / "p2", token=hub_server.token("read")
    )
    assert _local_files(got).items() >= _local_files(tiny_dataset).items()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_push_errors_are_one_clear_line(hub_server, tiny_dataset, clean_hub_env, tmp_path):
    write, read = hub_server.token("write"), hub_server.token("read")

    def push(**kwargs):
        args = {
            "root": tiny_dataset,
            "repo_id": REPO_ID,
            "endpoint": hub_server.url,
            "token": write,
            **kwargs,
        }
        with pytest.raises(HubError) as err:
            push_dataset(**args)
        message = str(err.value)
        assert "\n" not in message and message
        for token in (write, read, "hf_wrong"):
            assert token not in message
        return message

    closed = f"http://127.0.0.1:{_free_port()}"
    assert (
        push(endpoint=closed) == f"cannot reach the hub endpoint {closed}: "
        "[Errno 111] Connection refused"
    )
    with socket.socket() as silent:  # accepts connections, never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        url = f"http://127.0.0.1:{silent.getsockname()[1]}"
        assert "no answer in time" in push(endpoint=url, timeout=0.5)
    assert "cannot reach" in push(endpoint="http://no-such-host.invalid")

    msg = push(token="hf_wrong")
    assert "401" in msg and "token was rejected" in msg
    msg = push(token=None)
    assert "no Hugging Face token found" in msg and "HF_TOKEN" in msg
    msg = push(token=read)
    assert "403" in msg and "lacks the rights" in msg
    assert "ORG/NAME" in push(repo_id="not-a-namespaced-id")
    assert "invalid repo id" in push(repo_id="org/bad name")
    msg = push(root=tmp_path / "nothing-here")
    assert "no LeRobot dataset" in msg and "meta/info.json" in msg
    assert "not an http(s) URL" in push(endpoint="ftp://example")
    bad_card = shutil.copytree(tiny_dataset, tmp_path / "bad-card")
    (bad_card / "README.md").write_text("---\nlicense: [unclosed\n---\n# card\n")
    msg = push(root=bad_card)
    assert "README.md: invalid YAML header" in msg
    (bad_card / "README.md").write_bytes(b"---\nlicense: caf\xe9\n---\n")  # Latin-1
    assert "README.md is not UTF-8 text (invalid continuation byte" in push(root=bad_card)
    assert "is not a valid URL" in push(endpoint="http://[::1")  # passes the URL pattern
    not_info = shutil.copytree(tiny_dataset, tmp_path / "not-info")
    (not_info / "meta/info.json").write_text("[1, 2]")
    assert "is not a LeRobot info.json" in push(root=not_info)
    # None of the failures wrote anything.
    assert ("dataset", REPO_ID) not in hub_server.state.repos
