"""The C heap's policy: keep the memory a frame frees for the next frame, give a rare peak back.

`keep_freed_memory`: by default glibc serves every allocation above 128 kB (a scan's copies, its voxel keys, an
image's pyramid) with a fresh mmap and returns it to the OS on free, and trims the heap's top above a few MB, so the
next keyframe's arrays are faulted in again page by page. Measured on KITTI 04 (deployed, per frame): 750 page
faults in the tracker's process, 500 in the back end's, 740 in the loop closer's; the loop closer's scan thinning
took 7 ms a keyframe and registration's voxel downsampling 11 ms, against 3.7 and 8 ms with the memory kept
(MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES, TOP_PAD_BYTES below; 85k instead of 460k faults over 17 keyframes of
scans and features). The process then holds at most TRIM_THRESHOLD_BYTES of free memory above what it uses.

`release_free_memory`: after a global bundle adjustment (gtsam's graph and elimination of a whole map) the loop
worker's resident memory stayed ~330 MB above what it uses (4541-frame soak). `malloc_trim(0)` returns those pages.

Both are no-ops elsewhere than glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's ceiling for it on 64-bit
TRIM_THRESHOLD_BYTES = 64 << 20
TOP_PAD_BYTES = 16 << 20
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3  # malloc.h


def c_library() -> ctypes.CDLL | None:
    """The C library (glibc on Linux), or None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def keep_freed_memory() -> bool:
    """Have glibc keep freed memory for reuse instead of unmapping it (see the module doc); True when it took.
    For the processes whose per-frame work allocates the same large arrays again and again: plvo's worker processes
    and the application's tracking process. A library caller's process is left as it is."""
    c = c_library()
    if c is None or not hasattr(c, "mallopt"):
        return False
    return all(c.mallopt(param, value) == 1 for param, value in (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (_M_TOP_PAD, TOP_PAD_BYTES)))


def release_free_memory() -> bool:
    """Return the C heap's free pages to the OS (glibc's malloc_trim); True when it ran."""
    c = c_library()
    if c is None or not hasattr(c, "malloc_trim"):  # not glibc
        return False
    c.malloc_trim(0)
    return True
