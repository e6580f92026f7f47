"""The socket protocol every connection of the engine's loop reads with: one read
buffer for the whole loop (:data:`READ_BUFFER`) instead of asyncio's new 256 KiB
``bytes`` per read."""

from __future__ import annotations

import asyncio
from typing import Protocol

__all__ = ["READ_BUFFER", "HasReadBuffer", "Reader"]

#: How many bytes one read of a socket takes at most. The engine reads into one
#: buffer of its own (:class:`Reader`): asyncio's plain protocols get a new
#: 256 KiB ``bytes`` per read, which glibc serves above its mmap threshold, so
#: every 12-byte request cost an mmap, page faults, an mremap and a munmap (a TLB
#: shootdown across the process's threads): half the engine's CPU per request
#: (docs/performance.md). A Modbus/TCP ADU is at most 260 bytes.
READ_BUFFER = 64 * 1024


class HasReadBuffer(Protocol):
    """What a :class:`Reader` reads into: the engine's one buffer."""

    read_buffer: memoryview


class Reader(asyncio.BufferedProtocol):
    """A socket protocol that reads into the engine's one read buffer and hands
    ``data_received`` a ``bytes`` copy of exactly what was read (see
    :data:`READ_BUFFER`). The buffer is shared by every connection of the loop:
    asyncio fills it and calls :meth:`buffer_updated` in one step, in the loop's
    thread, so it is free again before the next read."""

    engine: HasReadBuffer

    def get_buffer(self, sizehint: int) -> memoryview:
        return self.engine.read_buffer

    def buffer_updated(self, nbytes: int) -> None:
        self.data_received(bytes(self.engine.read_buffer[:nbytes]))

    def data_received(self, data: bytes) -> None:
        raise NotImplementedError
