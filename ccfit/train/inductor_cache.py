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
  The vector width is read from those tests, so the files cut short go first."""

from __future__ import annotations

import struct
import sys
from pathlib import Path

ELF_HEADER_BYTES = 64
"""An ELF64 header's size: a shorter shared object is cut short."""


def prepare_inductor_cache() -> list[Path]:
    """Drop the shared objects cut short, then pin the cache key; returns the files dropped."""
    dropped = drop_truncated_kernels()
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
