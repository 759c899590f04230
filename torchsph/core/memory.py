"""The process's host-memory allocator: large freed blocks kept for reuse.

glibc's malloc hands a freed block above its mmap threshold (adaptive, at most 32 MiB)
back to the system, and trims the heap's free top beyond twice that. The next array of
that size is then new memory, and its first write costs a page fault per 4 KiB page:
about 0.5 ms per MB, as long as the arithmetic on it. A full-scene rebuild makes tens of
pair arrays of 10-30 MB, each new: the conduction operator's follow at the first steps
of ``perpendicular_350W`` took 440 ms, 217 ms with the blocks kept (measured, 1 thread).
:func:`keep_freed_blocks` sets the threshold to its largest value and stops the trimming,
so freed blocks are reused; the resident size then stays at its peak instead of falling
between rebuilds (the peak itself is the same). The heap also grows 1 GiB beyond what is
asked each time it grows (its top pad; address space, not memory, until written): the full
scene's first active-set refresh then spent no system time instead of 30-55 ms of page faults
(550 -> 500 ms, 1 thread, measured at stop 46; 256 MiB left 12-39 ms). ``TORCHSPH_MALLOC=system`` leaves the
allocator as it is; other C libraries (musl, macOS, Windows) are left alone.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD_MAX = 32 * 2**20  # glibc's largest accepted value on 64-bit
TOP_PAD = 2**30  # the heap grows by this much more than asked
_set = None


def keep_freed_blocks() -> bool:
    """Once per process: glibc malloc keeps freed blocks up to 32 MiB and the heap's free
    top for reuse. Returns whether the setting is in force."""
    global _set
    if _set is None:
        _set = False
        if sys.platform.startswith("linux") and os.environ.get("TORCHSPH_MALLOC", "") != "system":
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                mallopt = libc.mallopt
            except (OSError, AttributeError):  # not glibc
                return False
            mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
            _set = all(bool(mallopt(p, v)) for p, v in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX),
                                                          (M_TRIM_THRESHOLD, 2**31 - 1), (M_TOP_PAD, TOP_PAD)))
    return _set
