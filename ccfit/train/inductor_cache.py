"""Inductor's on-disk cache made safe to share between processes and runs.

Every process that compiles (`ccfit.train.compiled.compile_hot_paths`) calls
`prepare_inductor_cache` first. torch 2.11's cache has two holes this toolkit fell into:
- a shared object is linked straight to its final path, so a compile killed while linking (a
  session's end, a SLURM timeout) leaves a file cut short there, which every later process
  finds and uses instead of building it again. A kernel cut short fails to load ("file too
  short", pytorch#102539; a PnPBoxClose reference met one that a compile eleven hours before had
  left). A cut-short copy of the small library Inductor builds to test a vector instruction
  set fails that test, silently, and kernels are then compiled without the instruction set.
  Such files are removed (`drop_truncated_kernels`) and built again when next needed;
- what it writes into a CPU kernel but leaves out of the kernel's cache key (the thread count,
  the vector width) is set explicitly, so that it is in the key (`pin_inductor_cache_key`).
  The vector width is read from those tests, so the files cut short go first.

It also spares every compiling process Inductor's instruction-set tests: to learn which vector
instruction sets its kernels may use, Inductor builds a small library per candidate set and
loads it in a fresh interpreter that imports torch (about 15 s per process on 2 cores, beside
the run it delays). What they find is a fact of the machine, the compiler and torch, so the
first process on a machine records each pass and later ones read it (`settle_vec_isa_tests`),
whatever compile cache they use: the record lies where torch keeps its precompiled headers
(`machine_dir`), not in the cache, so an empty cache (a new `TORCHINDUCTOR_CACHE_DIR`, a
fresh clone's runs) compiles kernels again but does not test the machine again."""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import shutil
import struct
import sys
from pathlib import Path

ELF_HEADER_BYTES = 64
"""An ELF64 header's size: a shorter shared object is cut short."""


VEC_ISA_RECORD = "ccfit-vec-isa.json"
"""The file in `machine_dir` that records the instruction-set tests passed."""


def prepare_inductor_cache() -> list[Path]:
    """Drop the shared objects cut short, settle the instruction-set tests, then pin the cache
    key; returns the files dropped."""
    dropped = drop_truncated_kernels()
    settle_vec_isa_tests()
    pin_inductor_cache_key()
    return dropped


def drop_truncated_kernels() -> list[Path]:
    """Remove the shared objects under Inductor's cache that a dynamic loader would refuse as
    cut short (`is_whole_elf`), each under the lock Inductor builds that kernel under, so a
    kernel another process is linking now is left to it. Returns the files removed. Only on
    Linux, whose shared objects are ELF files (macOS's are not, and all would look cut)."""
    if not sys.platform.startswith("linux"):
        return []
    from filelock import FileLock, Timeout
    from torch._inductor.codecache import cache_dir, get_lock_dir

    dropped = []
    for path in sorted(Path(cache_dir()).rglob("*.so")):
        if is_whole_elf(path):
            continue
        key = path.name.split(".")[0]  # Inductor names a kernel's files <key>[.main].so
        try:
            with FileLock(str(Path(get_lock_dir()) / f"{key}.lock"), timeout=0):
                if path.exists() and not is_whole_elf(path):
                    path.unlink()
                    dropped.append(path)
        except Timeout:  # being built now; its builder finishes it
            continue
    for path in dropped:
        print(f"ccfit: note: removed {path} from Inductor's cache: cut short (its compile was "
              "killed); it is built again when needed", file=sys.stderr)  # fmt: skip
    return dropped


def is_whole_elf(path: Path) -> bool:
    """Whether `path` holds a whole 64-bit ELF file, as far as its header tells: the header
    is there and the section header table it points to (which a linker writes last) lies
    inside the file. A file that is gone counts as whole: there is nothing to remove."""
    try:
        size = path.stat().st_size
        with path.open("rb") as f:
            head = f.read(ELF_HEADER_BYTES)
    except FileNotFoundError:
        return True
    if len(head) < ELF_HEADER_BYTES or head[:4] != b"\x7fELF" or head[4] != 2:
        return False
    order = "<" if head[5] == 1 else ">"
    (table,) = struct.unpack_from(f"{order}Q", head, 40)
    entry, entries = struct.unpack_from(f"{order}HH", head, 58)
    return table + entry * entries <= size


def pin_inductor_cache_key() -> None:
    """Set what torch 2.11 writes into Inductor's CPU kernels but leaves out of their cache
    key, so that it is in the key: the thread count and the vector width (below)."""
    pin_inductor_threads()
    pin_inductor_vector_width()


def pin_inductor_threads() -> int:
    """Compile CPU kernels for this process's thread count, named in Inductor's cache key.

    Inductor writes the thread count into its CPU kernels (`#pragma omp ... num_threads(N)`),
    by default `torch.get_num_threads()` at compile time, but torch 2.11 leaves that count out
    of its on-disk cache key (pytorch#160812): a run with `--train.torch_threads 1` then loads
    the kernels a 2-thread process compiled, and two such runs on two cores spin four OpenMP
    threads (found in a 1-thread TD-MPC2 run at 1M, 42% of its time in libgomp's spin-wait),
    and a kernel's sums may be split otherwise than a same-seed run compiled afresh. The count
    set explicitly is part of the key. Returns it."""
    import torch._inductor.config

    torch._inductor.config.cpp.threads = torch.get_num_threads()
    return torch._inductor.config.cpp.threads


def pin_inductor_vector_width() -> int:
    """Compile CPU kernels for this process's vector width, named in Inductor's cache key.

    Inductor picks the vector instruction set of its CPU kernels when it compiles (the widest
    the CPU has, or what `ATEN_CPU_CAPABILITY` lowers it to) and writes its width into their
    loops (a step of 8 floats for AVX2, 16 for AVX-512), but torch 2.11 leaves the pick out of
    its on-disk cache key, and a cached graph's kernels are built when they are loaded, for the
    loading process's pick. On an AVX-512 machine, a graph a process had compiled under
    `ATEN_CPU_CAPABILITY=avx2` was served to processes without it: their kernels stored 16
    floats per step of 8, and every `cpu`-preset TD-MPC2 run aborted with heap corruption at
    its first evaluation, in the plan (7 of 7; with a fresh cache, none). The width set
    explicitly is part of the key and picks the same instruction set. Returns it."""
    import torch._inductor.config
    from torch._inductor import cpu_vec_isa

    config = torch._inductor.config.cpp
    config.simdlen = None  # what this process would pick unpinned (ATEN_CPU_CAPABILITY's)
    config.simdlen = cpu_vec_isa.pick_vec_isa().bit_width()
    return config.simdlen


def settle_vec_isa_tests() -> None:
    """Run each of Inductor's instruction-set tests once per machine, not once per process.

    Inductor keeps an x86 vector instruction set that the CPU reports only if a small library
    built with it (and one more per extension: AVX512-BF16, VNNI, AMX) loads in a fresh
    interpreter (`VecISA.check_build`): a test of the compiler and of torch's build on this
    CPU, which every compiling process repeats. Here each test's pass is recorded in
    `machine_dir` (not in the cache: an empty cache tests nothing again), keyed by what
    decides it (`vec_isa_key`, the compiler flags, the test's code), and a test on record is
    not run again. A failure is not recorded: it may come from a test library cut short,
    which `drop_truncated_kernels` removes, and the next process tests again, as Inductor
    alone would. Installed once per process."""
    from torch._inductor import cpu_vec_isa

    tested = cpu_vec_isa.VecISA.check_build
    if getattr(tested, "remembered", False):
        return

    def check_build(isa, code: str) -> bool:
        record = _vec_isa_record()
        key = hashlib.sha256(f"{vec_isa_key()}|{isa._arch_flags}|{code}".encode()).hexdigest()
        if _read_json(record).get(key[:24]):
            return True
        passed = tested(isa, code)
        if passed:
            _add_vec_isa_pass(record, key[:24])
        return passed

    check_build.remembered = True
    cpu_vec_isa.VecISA.check_build = check_build


def machine_dir() -> Path:
    """Where torch keeps what a machine's compiles share whatever their cache directory (its
    precompiled headers): `<temp dir>/torchinductor_<user>`, which `TORCHINDUCTOR_CACHE_DIR`
    does not move."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    return Path(default_cache_dir())


def _vec_isa_record() -> Path:
    return machine_dir() / VEC_ISA_RECORD


@functools.cache
def vec_isa_key() -> str:
    """What Inductor's instruction-set tests depend on beyond their own code and flags, hashed:
    the instruction sets the CPU reports, the C++ compiler (its file's path, size and time;
    asking it its version costs half a second) and torch's build."""
    import torch
    from torch._inductor import cpu_vec_isa
    from torch._inductor.cpp_builder import get_cpp_compiler

    compiler = shutil.which(get_cpp_compiler()) or get_cpp_compiler()
    try:
        stat = os.stat(compiler)
        compiler_id = f"{os.path.realpath(compiler)}:{stat.st_size}:{stat.st_mtime_ns}"
    except OSError:
        compiler_id = compiler
    reported = [*cpu_vec_isa.x86_isa_checker(), *(["avx512_bf16"] if
                torch.cpu._is_avx512_bf16_supported() else [])]  # fmt: skip
    parts = [platform.machine(), ",".join(reported), compiler_id, torch.__version__,
             str(torch.version.git_version)]  # fmt: skip
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]


def _read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def _add_vec_isa_pass(record: Path, key: str) -> None:
    """Add a passed test to `record`, atomically (processes testing at once each write what
    they found; a pass another wrote meanwhile may be lost and is tested again later)."""
    from ccdata.atomic import atomic_write_text

    known = {**_read_json(record), key: True}
    atomic_write_text(record, json.dumps(known, indent=2, sort_keys=True) + "\n")
