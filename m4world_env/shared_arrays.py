"""Named numpy arrays in one shared-memory block, laid out once and attached by other processes.

The vector env's simulation workers (:mod:`m4world_env.workers`) write each sub-env's condition
arrays here and the main process reads them: the pipes between them carry only small messages.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

ALIGN_BYTES = 64  # each array starts on a cache line
NAME_PREFIX = "m4w_"  # /dev/shm/m4w_*: the segments of M4World vector envs


@dataclass(frozen=True)
class ArraySpec:
    """One array of a :class:`SharedArrays` block: its shape, dtype and byte offset."""

    shape: tuple[int, ...]
    dtype: str
    offset: int


@dataclass(frozen=True)
class SharedLayout:
    """What another process needs to attach a :class:`SharedArrays` block: its name and arrays."""

    name: str
    size: int
    arrays: dict[str, ArraySpec]


def plan_layout(arrays: dict[str, tuple[tuple[int, ...], np.dtype]], name: str) -> SharedLayout:
    """Offsets of ``arrays`` (name -> (shape, dtype)) packed in one block, each aligned to
    :data:`ALIGN_BYTES`."""
    specs, offset = {}, 0
    for key, (shape, dtype) in arrays.items():
        dtype = np.dtype(dtype)
        specs[key] = ArraySpec(tuple(int(n) for n in shape), dtype.str, offset)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        offset += -(-nbytes // ALIGN_BYTES) * ALIGN_BYTES
    return SharedLayout(name, max(offset, 1), specs)


class SharedArrays:
    """Numpy views (``arrays[name]``) of one shared-memory block. The process that creates it
    :meth:`unlink`\\ s it when done; every process :meth:`close`\\ s its own mapping."""

    def __init__(self, layout: SharedLayout, memory: shared_memory.SharedMemory, owner: bool) -> None:
        self.layout, self._memory, self.owner = layout, memory, owner
        self.arrays = {
            key: np.ndarray(spec.shape, np.dtype(spec.dtype), memory.buf, spec.offset)
            for key, spec in layout.arrays.items()
        }

    @classmethod
    def create(cls, arrays: dict[str, tuple[tuple[int, ...], np.dtype]]) -> SharedArrays:
        """A new zeroed block holding ``arrays`` (name -> (shape, dtype))."""
        layout = plan_layout(arrays, f"{NAME_PREFIX}{secrets.token_hex(8)}")
        memory = shared_memory.SharedMemory(name=layout.name, create=True, size=layout.size)
        return cls(layout, memory, owner=True)

    @classmethod
    def attach(cls, layout: SharedLayout) -> SharedArrays:
        """The block another process created, by its layout."""
        return cls(layout, shared_memory.SharedMemory(name=layout.name), owner=False)

    @property
    def name(self) -> str:
        return self.layout.name

    def close(self) -> None:
        """Drop this process's mapping (the views become invalid); the block stays for the others."""
        self.arrays = {}
        self._memory.close()

    def unlink(self) -> None:
        """Close and remove the block (its creator, once every process is done with it)."""
        self.close()
        if self.owner:
            self._memory.unlink()
