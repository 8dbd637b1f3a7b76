"""Give the C heap's free pages back to the system (glibc `malloc_trim`), for the serve process.

Measured on `bench/bench_soak.py` (issue 24, glibc 2.36): frames are decoded on Zenoh's
threads and freed on the robots' session threads, 1-2 MB arrays dozens of times a second;
glibc keeps the freed memory in its arenas (the serve process's heap in use stayed ~250 MB
while the free memory it kept grew by 20 MB a minute, RSS with it). `malloc_trim(0)` returns
the free pages of every arena to the system (madvise); the service calls it from its
maintenance thread every `service.malloc_trim_s` seconds. A no-op where the C library has no
`malloc_trim` (not glibc)."""
from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger("mnemoslam.malloc")

_trim = None


def _load():
    global _trim
    if _trim is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _trim = libc.malloc_trim
            _trim.argtypes, _trim.restype = [ctypes.c_size_t], ctypes.c_int
        except (OSError, AttributeError):
            _trim = False
    return _trim


def trim() -> bool:
    """malloc_trim(0): True when memory was given back, False when none was (or no glibc)."""
    f = _load()
    if not f:
        return False
    return bool(f(0))
