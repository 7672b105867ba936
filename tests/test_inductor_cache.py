"""Inductor's on-disk cache after a compile was killed: a kernel's shared object cut short is
removed and compiled again, not loaded ("file too short")."""

from __future__ import annotations

import _json
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from filelock import FileLock

from ccfit.train.inductor_cache import VEC_ISA_RECORD, drop_truncated_kernels, is_whole_elf

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="shared objects are ELF files on Linux only"
)


def _elf() -> Path:
    """A real shared object (a module of Python's own) to cut short."""
    return Path(_json.__file__)


def _cut(src: Path, dst: Path, size: int) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(src.read_bytes()[:size])
    return dst


def test_only_shared_objects_cut_short_are_dropped_and_not_while_being_built(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path))
    elf = _elf()
    whole = tmp_path / "ab" / "cabwhole.main.so"
    whole.parent.mkdir()
    shutil.copyfile(elf, whole)
    size = elf.stat().st_size
    empty = _cut(elf, tmp_path / "cd" / "ccdempty.main.so", 0)
    header_only = _cut(elf, tmp_path / "cd" / "ccdheader.so", 40)  # not even the header
    tail_missing = _cut(elf, tmp_path / "ef" / "cefnotail.main.so", size - 100)
    building = _cut(elf, tmp_path / "ef" / "cefbuilding.main.so", size // 2)
    source = _cut(elf, tmp_path / "ef" / "cefbuilding.main.cpp", 0)  # not a shared object
    assert is_whole_elf(whole) and is_whole_elf(tmp_path / "gone.so")
    assert not any(map(is_whole_elf, (empty, header_only, tail_missing, building)))
    with monkeypatch.context() as darwin:  # Mach-O files there: none is judged
        darwin.setattr(sys, "platform", "darwin")
        assert drop_truncated_kernels() == [] and empty.exists()
    (tmp_path / "locks").mkdir()
    with FileLock(str(tmp_path / "locks" / "cefbuilding.lock")):  # another process links it
        dropped = drop_truncated_kernels()
    assert sorted(dropped) == sorted([empty, header_only, tail_missing])
    assert whole.exists() and building.exists() and source.exists()
    assert not any(p.exists() for p in dropped)
    assert drop_truncated_kernels() == [building]  # once its lock is free, it was left cut


CHILD = """
import json, sys
tests = []  # Inductor loads each instruction-set test's library in a fresh interpreter
sys.addaudithook(lambda event, args: tests.append(1) if event == "subprocess.Popen"
                 and "LoadLibrary" in " ".join(map(str, args[1] or ())) else None)
import torch
from torch._inductor import cpu_vec_isa
from ccfit.train.inductor_cache import pin_inductor_cache_key, prepare_inductor_cache
prepare_inductor_cache() if sys.argv[2] == "prepare" else pin_inductor_cache_key()
x = torch.arange(64 * 64, dtype=torch.float32).reshape(64, 64) / 100
f = torch.compile(lambda t: (t.sin() * float(sys.argv[1])).sum(0), backend="inductor")
value = f(x).sum().item()
isas = [(str(isa), isa.build_arch_flags()) for isa in cpu_vec_isa.valid_vec_isa_list()]
print(json.dumps({"value": value, "tests": len(tests), "isas": isas,
                  "picked": str(cpu_vec_isa.pick_vec_isa())}))
"""


@pytest.mark.integration  # five compiling processes, four from an empty cache: ~190 s of a core
def test_shared_objects_cut_short_by_a_killed_compile_are_built_again(tmp_path):
    """Each compile a process of its own, as runs are (a process that loaded a library gets it
    again whatever its file now holds). The first process in an empty cache runs Inductor's
    instruction-set tests and records them; a later one starts none and picks the same set.
    Then what torch 2.11 does with files cut short: the libraries that test each vector
    instruction set fail their tests silently, and the kernel is compiled otherwise (a kernel
    cut short fails to load: "file too short", as the PnPBoxClose reference met it). Dropped
    first, every file is built again under its name: the same kernel, with the same set."""
    from torch._inductor import cpu_vec_isa

    if not cpu_vec_isa.valid_vec_isa_list():
        pytest.skip("Inductor finds no vector instruction set here: cut tests change nothing")
    cache, temp = tmp_path / "cache", tmp_path / "tmp"  # a cache and a machine of its own
    temp.mkdir()
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache), "TMPDIR": str(temp)}
    scale = "1.25"

    def compile_in_a_process(how: str, cache_dir: Path = cache) -> tuple[dict, str]:
        args = [sys.executable, "-c", CHILD, scale, how]
        done = subprocess.run(args, env={**env, "TORCHINDUCTOR_CACHE_DIR": str(cache_dir)},
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout.splitlines()[-1]), done.stderr

    def shared_objects() -> set[Path]:
        return set(cache.rglob("*.so"))

    first, _ = compile_in_a_process("prepare")
    record = next(temp.glob(f"torchinductor_*/{VEC_ISA_RECORD}"))  # the machine's
    assert not list(cache.rglob(VEC_ISA_RECORD))
    if platform.machine() in ("x86_64", "AMD64"):  # Inductor tests sets in interpreters on x86
        assert first["tests"] > 0
    later, _ = compile_in_a_process("prepare")
    assert later == {**first, "tests": 0}
    # An empty cache on the same machine compiles again but tests nothing again.
    elsewhere, _ = compile_in_a_process("prepare", tmp_path / "another-cache")
    assert elsewhere == {**first, "tests": 0}
    # Without its verdict on record, each process tests the instruction sets again (as a
    # process does where a set failed): what those tests make of their libraries cut short.
    record.unlink()
    built = shared_objects()  # the instruction set tests' libraries and the kernel's
    assert len(built) > 1 and all(map(is_whole_elf, built))
    for path in built:
        path.write_bytes(b"")  # a killed linker had created its output
    compile_in_a_process("pin")
    assert shared_objects() - built  # compiled otherwise, with the cut files left in place
    again, stderr = compile_in_a_process("prepare")
    assert stderr.count("cut short") == len(built)
    assert again["value"] == first["value"] and again["isas"] == first["isas"]
    assert built <= shared_objects() and all(map(is_whole_elf, built))
