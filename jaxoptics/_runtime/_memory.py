"""Keep freed memory in the process: what makes XLA's CPU kernels run at their speed on Linux.

XLA on the CPU allocates every output and temporary buffer with `malloc`. glibc serves blocks
larger than its mmap threshold (at most 32 MiB) with a fresh `mmap` and returns them with `munmap`
on free, so every call of a jitted kernel on 10^7 float32 values writes its 40 MB output into
pages the kernel has never seen: one page fault per 4 KiB, about 1 ns per element on this machine,
more than the arithmetic of the exact Fresnel equations (measured in the benchmark's "what bounds
XLA on the CPU" table). Renderers' own runtimes (Dr.Jit, for one) keep a cache of freed blocks
for this reason.

`keep_freed_memory()` does the same for the whole process, through glibc's documented `mallopt`:
no block is served by `mmap` any more, and freed memory is not trimmed back to the system, so the
next call reuses pages that are already mapped. The cost: the process keeps its peak heap size
for its lifetime (nothing is returned to the system until it exits), and a fragmented heap can
hold more than it uses. It is opt-in and process-wide, like `LD_PRELOAD`-ing jemalloc or tcmalloc
(the usual advice for CPU deep-learning frameworks) or setting, before Python starts,
`GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=4294967295`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

# glibc's mallopt parameters (malloc.h) and its documented defaults
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_MMAP_MAX = -4
_DEFAULT_TRIM_THRESHOLD = 128 * 1024
_DEFAULT_MMAP_THRESHOLD = 128 * 1024
_DEFAULT_MMAP_MAX = 65536


@functools.cache
def _glibc():
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version  # only glibc has mallopt with these meanings
        libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.mallopt.restype = ctypes.c_int
        return libc
    except (OSError, AttributeError):
        return None


def keep_freed_memory(*, enable: bool = True) -> bool:
    """Make glibc's `malloc` keep freed memory mapped, for reuse by the next kernel call.

    **Arguments:**

    - `enable`: `True` to keep freed memory (no `mmap`-served blocks, no trimming); `False` to
      restore glibc's default values (128 KiB thresholds). Not its default behaviour: glibc turns
      its adaptive mmap threshold off for good once any of these is set, so afterwards every block
      above 128 KiB is served by a fresh `mmap` (a 10^4-curve `fit_eta`, whose temporaries glibc
      would otherwise reuse, then page-faults in every call: 0.044 against 0.020 s, measured). Only
      a new process is back in the default state.

    **Returns:** `True` if the setting was applied, `False` where it cannot be (not glibc: macOS,
    Windows, musl), in which case nothing changed.

    Process-wide and opt-in: call it once at start-up in a program that runs large jitted kernels
    on the CPU many times. A freed block is then reused by the next allocation that fits it, with
    no page faults. Inside XLA that holds for most calls, not for each: outputs are allocated by
    XLA's worker threads, each from its own malloc arena, small allocations in between can split a
    freed block (the heap then grows again until it holds the working set), and glibc unmaps a
    per-thread heap other than an arena's first once it is entirely free, whatever the settings.
    Measured over 30 calls of a kernel with a 40 MB output: the first 10 to 20 calls fault as the
    arenas grow; of the last 10, none fault on one machine and half do on another. The benchmark's
    "What bounds XLA on the CPU" table measures the effect (10^7 float32 values: a copy kernel and
    `jo.fresnel` with and without it; see the performance page of the documentation).
    The price is memory: the heap keeps its peak size until the process exits.
    """
    libc = _glibc()
    if libc is None:
        return False
    if enable:
        ok = libc.mallopt(_M_MMAP_MAX, 0) and libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    else:
        ok = (libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX) and libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD)
              and libc.mallopt(_M_MMAP_THRESHOLD, _DEFAULT_MMAP_THRESHOLD))
    return bool(ok)
