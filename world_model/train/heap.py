"""Keep freed CPU memory in the process heap, so eager PyTorch stops page-faulting every call.

One eager forward of the default student for 8 envs allocates ~200 MB of activations in tensors
of 0.1-10 MB. glibc's ``malloc`` serves every block above its mmap threshold (128 KiB at start;
it only rises to the largest block freed so far) with a fresh ``mmap`` and hands a freed heap top
larger than its trim threshold back to the OS. Every forward therefore touched ~55,000 new pages,
and the kernel zeroing them cost about a quarter of the forward on the 2-core CPU this project
targets (``m4world bench model --heaps retain default`` measures both, with the
page faults per forward).

:func:`retain_freed_memory` raises both thresholds with ``mallopt`` (glibc only; elsewhere it
does nothing and says so): blocks up to ``mmap_threshold_bytes`` come from the heap and freed
memory stays mapped for the next call. The process's peak memory does not grow (the freed
blocks are reused); its resident size just no longer shrinks after a peak. The setting is
process-wide, so it is applied by the programs that choose it (the train CLIs unless
``--default-heap``; ``m4world bench model --heaps retain``), never on import. The env does
not apply it: a process running the env already raises glibc's dynamic mmap threshold by freeing
large blocks, and an 8-env vector step measured no faster with it.

Torch-free at import.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
from dataclasses import dataclass

# mallopt parameter numbers, from glibc's <malloc.h>.
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3


@dataclass(frozen=True)
class HeapConfig:
    """glibc ``mallopt`` settings applied by :func:`retain_freed_memory`."""

    # Blocks up to this size come from the heap. 32 MiB is glibc's documented maximum on 64-bit
    # systems (DEFAULT_MMAP_THRESHOLD_MAX); the largest activation of an 8-env step (the VAE
    # decoder's first full-resolution map) is ~19 MB.
    mmap_threshold_bytes: int = 32 << 20
    # Free memory at the heap top is returned to the OS only beyond this.
    trim_threshold_bytes: int = 1 << 30
    # Extra memory requested whenever the heap grows, so it grows in few steps.
    top_pad_bytes: int = 64 << 20


_applied: HeapConfig | None = None


def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def retain_freed_memory(config: HeapConfig | None = None) -> bool:
    """Apply ``config`` (default :class:`HeapConfig`) to this process's glibc allocator.

    Returns True when glibc accepted every setting (also when an equal config was applied before),
    False on other C libraries or platforms, where nothing changes. Process-wide and lasting: call
    it from a program's entry point, not from library code a host application imports."""
    global _applied
    config = config or HeapConfig()
    if _applied == config:
        return True
    libc = _glibc()
    if libc is None:
        return False
    settings = (
        (_M_MMAP_THRESHOLD, config.mmap_threshold_bytes),
        (_M_TRIM_THRESHOLD, config.trim_threshold_bytes),
        (_M_TOP_PAD, config.top_pad_bytes),
    )
    ok = all(libc.mallopt(ctypes.c_int(param), ctypes.c_int(value)) == 1 for param, value in settings)
    _applied = config if ok else None
    return ok


def heap_retained() -> HeapConfig | None:
    """The config :func:`retain_freed_memory` applied in this process, or None."""
    return _applied
