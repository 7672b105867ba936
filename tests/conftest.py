"""Shared pytest fixtures, and the order in which pytest-xdist hands out test files."""

import atexit
import functools
import os
import shutil
import tempfile
from pathlib import Path

import pytest

# No test reads or writes the user's LeRobot cache: a suite dataset generated there for real
# runs changes what `--seed_dataset auto` resolves to, and so a test's result (a dry-run sweep
# over BinPnP passed only where BinPnP had been generated). Set before LeRobot is imported,
# which reads it once; subprocesses inherit it. Tests that need a dataset make a tiny one.
_LEROBOT_HOME = tempfile.mkdtemp(prefix="ccbench-tests-lerobot-")
os.environ["HF_LEROBOT_HOME"] = _LEROBOT_HOME
atexit.register(shutil.rmtree, _LEROBOT_HOME, ignore_errors=True)

try:
    from hubserver import HubServer
    from short_episodes import EPISODE_STEPS
except ImportError:  # tests/ imported as a package
    from tests.hubserver import HubServer
    from tests.short_episodes import EPISODE_STEPS


@pytest.fixture
def hub_server(tmp_path_factory):
    """A Hub-protocol server on 127.0.0.1 (random free port), shut down after the test.

    It accepts one token with the "write" role and one with the "read" role:
    `hub_server.token("write")`, `hub_server.token("read")`.
    """
    server = HubServer(
        tmp_path_factory.mktemp("hub"),
        {"hf_test_write_token": "write", "hf_test_read_token": "read"},
    )
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def short_episodes():
    """The tests' short episode length (`short_episodes.EPISODE_STEPS`), for the test to pass
    where a run, an environment or an evaluator takes its episode length."""
    return EPISODE_STEPS


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One torch thread in every test: tiny networks on a shared 2-core machine run ~10x faster
    than oversubscribed, and one thread fixes the reduction order (determinism checks)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@functools.cache
def slurm_unavailable() -> str | None:
    """Why the tests marked `slurm` cannot run here (None when sbatch, sinfo and sacct answer):
    the probe `ccdata generate` and `ccfit sweep` make before they submit."""
    from ccdata.slurm import LaunchError, check_slurm

    try:
        check_slurm()
    except LaunchError as err:
        return str(err)
    return None


@pytest.fixture(autouse=True)
def one_slurm_test_at_a_time(request):
    """Tests marked `slurm` share the one-node cluster and its partitions (one of them preempts
    the other): under pytest-xdist, a lock file keeps them from running at the same time."""
    if request.node.get_closest_marker("slurm") is None:
        yield
        return
    import fcntl
    import tempfile

    with open(os.path.join(tempfile.gettempdir(), "ccbench-slurm-tests.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def pytest_runtest_setup(item):
    """Skip a `gpu` test without CUDA. Skip a `slurm` test when no SLURM answers, with the
    reason; fail it instead when CCBENCH_REQUIRE_SLURM is set (CI sets it once its SLURM is
    up)."""
    if item.get_closest_marker("gpu") is not None:
        import torch

        if not torch.cuda.is_available():
            pytest.skip("no CUDA device")
    if item.get_closest_marker("slurm") is None:
        return
    reason = slurm_unavailable()
    if reason is None:
        return
    if os.environ.get("CCBENCH_REQUIRE_SLURM"):
        pytest.fail(f"SLURM is required here (CCBENCH_REQUIRE_SLURM) but: {reason}")
    pytest.skip(f"no usable SLURM: {reason}")


# ------------------------------------------------------------------ xdist scheduling

SLURM_FILES = ("test_slurm_generate.py", "test_sweep_slurm.py")
LONGEST_FIRST = (
    *SLURM_FILES, "test_record.py", "test_curriculum.py", "test_offline.py", "test_compile.py",
    "test_parallel.py", "test_tasks_contract.py",
    "test_analysis.py", "test_pretrain.py", "test_data.py", "test_dreamerv3_loop.py",
    "test_seam.py", "test_loop.py", "test_policies.py", "test_tasks_grasp_blocks.py",
    "test_cards.py", "test_dataset_cli.py",
)  # fmt: skip
"""Test files of more than ~40 s (2026-11 file totals under `--durations`), longest first (the
two SLURM files run as one unit); the rest follow in collection order."""


def pytest_collection_modifyitems(config, items):
    """Longest files first: under `--dist loadfile` xdist hands files out in collection order
    as workers free up, so a long file collected last keeps one worker busy while the other
    idles. (xdist's own reordering, by test count, sends files of a few long tests last.)"""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(Path(str(item.path)).name, len(rank)))


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, absent under `-p no:xdist`
def pytest_xdist_make_scheduler(config, log):
    """`--dist loadfile` with the SLURM files as one unit (they take the cluster in turn; on two
    workers one would wait on the other's lock) and the collection order kept."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class LongestFirstFileScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "slurm" if Path(path).name in SLURM_FILES else path

    config.option.loadscopereorder = False
    return LongestFirstFileScheduling(config, log)
