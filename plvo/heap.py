"""Give the C heap's free memory back to the operating system after a large, rare allocation peak.

glibc keeps freed heap pages for reuse; after a global bundle adjustment (gtsam's graph and elimination of a whole
map) the loop worker's resident memory stayed ~330 MB above what it uses (4541-frame soak). `malloc_trim(0)`
returns those pages. It is a no-op elsewhere than glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys


def release_free_memory() -> bool:
    """Return the C heap's free pages to the OS (glibc's malloc_trim); True when it ran."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        return False
    return True
