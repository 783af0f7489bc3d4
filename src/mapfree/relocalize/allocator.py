"""Keep freed image-sized buffers in the process heap, so per-frame work does not pay fresh page faults.

Per pair, feature extraction and matching allocate and free buffers of 1-16 MB (image pyramids, the 2048 x 2048
descriptor distance matrix). glibc's defaults serve such sizes by ``mmap`` and give them back on ``free``
(dynamic mmap threshold, top-of-heap trimming at twice it), so the next pair faults the same pages in again:
about 14 000 minor page faults per ``sift_emat_sensor`` pair on realmini-dev, a quarter of its time on a CPU
core. Whether a process escaped that used to depend on what earlier code had left in the heap. Fixing the
thresholds makes the fast state the normal one; the cost is up to ``TRIM_BYTES`` of free heap kept mapped.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["keep_heap_warm", "MMAP_BYTES", "TRIM_BYTES"]

MMAP_BYTES = 32 << 20  # glibc's largest allowed mmap threshold on 64-bit: buffers below it come from the heap
TRIM_BYTES = 256 << 20  # free heap above this is given back to the system
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)
_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
_done: bool | None = None


def keep_heap_warm() -> bool:
    """Set glibc's mmap and trim thresholds for this process (once); True when they are in effect.

    A no-op (False) off glibc, or when the user set ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
    (their choice wins), or with ``MAPFREE_MALLOC_DEFAULTS=1``.
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux") or os.environ.get("MAPFREE_MALLOC_DEFAULTS") == "1":
        return False
    if any(v in os.environ for v in _ENV):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES))
    return _done
