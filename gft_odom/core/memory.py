"""Giving freed heap back to the operating system after a very large scan.

glibc keeps freed heap for reuse; after one huge scan that is tens of MB of resident memory
for good unless it is trimmed (docs/robustness.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util

# After a scan this big, give the freed heap back to the OS at the next call: glibc keeps it
# otherwise (a 3-million-point scan left +37 MB RSS for good, docs/robustness.md).
TRIM_AFTER_POINTS = 500_000
# ... and at each call for 2 s at 10 Hz after it: freeing its big blocks raises glibc's mmap
# threshold, so the next scans' blocks come from the heap and stay there until a trim (with
# deskew, one trim left +12 MB against a normal scan, three +12 MB, twenty +3.5 MB; a trim
# costs ~0.01 ms).
TRIMS_AFTER_A_LARGE_SCAN = 20


def _malloc_trim():
    """glibc's malloc_trim(0) when available (a no-op elsewhere)."""
    name = ctypes.util.find_library('c')
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    return (lambda: trim(0)) if trim is not None else (lambda: 0)


release_free_memory = _malloc_trim()
