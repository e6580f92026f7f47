"""Capture files: the byte layout of classic pcap (:class:`PcapWriter`) and pcapng
(:class:`PcapngWriter`, which the tests use to cover every block type the reader
accepts). They write records they are given; what goes in a record is
:mod:`mbmon.io.pcap.packets`.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Self

from mbmon.io.pcap.packets import LINKTYPE_ETHERNET

_PCAP_MAGIC_US = 0xA1B2C3D4
_PCAP_MAGIC_NS = 0xA1B23C4D


class _CaptureFile:
    """The output file of a capture writer: a path (opened and closed here) or a
    binary file object (flushed, and left open for its owner, on :meth:`close`)."""

    def __init__(self, out: str | Path | BinaryIO) -> None:
        if isinstance(out, str | Path):
            self._f: BinaryIO = open(out, "wb")
            self._own = True
        else:
            self._f = out
            self._own = False

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if self._own:
            self._f.close()
        else:
            self._f.flush()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class PcapWriter(_CaptureFile):
    """Classic pcap file with one link type (micro- or nanosecond timestamps).

    ``out`` is a path or a binary file object (left open on :meth:`close` when it
    was given as an object). Records longer than ``snaplen`` are cut to it.
    """

    def __init__(
        self,
        out: str | Path | BinaryIO,
        linktype: int = LINKTYPE_ETHERNET,
        *,
        snaplen: int = 262144,
        nanosecond: bool = False,
        big_endian: bool = False,
    ) -> None:
        super().__init__(out)
        self._e = ">" if big_endian else "<"
        self._scale = 1_000_000_000 if nanosecond else 1_000_000
        self._snaplen = snaplen
        self._rec = struct.Struct(self._e + "IIII")
        magic = _PCAP_MAGIC_NS if nanosecond else _PCAP_MAGIC_US
        self._f.write(struct.pack(self._e + "IHHiIII", magic, 2, 4, 0, 0, snaplen, linktype))

    def write(self, ts: float, data: bytes, *, orig_len: int | None = None) -> None:
        """One record at ``ts`` (epoch seconds); ``orig_len`` defaults to ``len(data)``."""
        units = round(ts * self._scale)
        sec, frac = divmod(units, self._scale)
        cap = data[: self._snaplen]
        self._f.write(
            self._rec.pack(sec, frac, len(cap), len(data) if orig_len is None else orig_len)
        )
        self._f.write(cap)


class PcapngWriter(_CaptureFile):
    """Pcapng file: sections, interfaces, and every packet block type (EPB, SPB, PB).

    Interfaces are added with :meth:`add_interface` (returns the interface id);
    ``tsresol`` is the raw ``if_tsresol`` option byte (6 = microseconds, the
    default; 9 = nanoseconds; 0x80 | n = 2^-n seconds).
    """

    def __init__(
        self, out: str | Path | BinaryIO, *, big_endian: bool = False, comments: Sequence[str] = ()
    ) -> None:
        super().__init__(out)
        self._e = ">" if big_endian else "<"
        self._ifaces: list[tuple[int, int]] = []  # (resolution divisor, snaplen)
        self.new_section(comments=comments)

    def _block(self, block_type: int, body: bytes) -> None:
        body += b"\0" * (-len(body) % 4)
        total = len(body) + 12
        self._f.write(struct.pack(self._e + "II", block_type, total) + body)
        self._f.write(struct.pack(self._e + "I", total))

    def _option(self, code: int, value: bytes) -> bytes:
        return struct.pack(self._e + "HH", code, len(value)) + value + b"\0" * (-len(value) % 4)

    def _comments(self, comments: Sequence[str]) -> bytes:
        """One ``opt_comment`` (option 1, UTF-8) per comment; the end-of-options
        marker is the caller's."""
        return b"".join(self._option(1, text.encode("utf-8")) for text in comments)

    def _section_header(self, comments: Sequence[str] = ()) -> bytes:
        """The SHB body: byte-order magic, version 1.0, unknown section length,
        ``shb_comment`` for each of ``comments``, ``shb_userappl`` mbmon."""
        body = struct.pack(self._e + "IHHq", 0x1A2B3C4D, 1, 0, -1)
        return body + self._comments(comments) + self._option(4, b"mbmon") + self._option(0, b"")

    def new_section(self, *, big_endian: bool | None = None, comments: Sequence[str] = ()) -> None:
        """Start a section (SHB, with a ``shb_comment`` for each of ``comments``);
        interfaces of earlier sections are forgotten."""
        if big_endian is not None:
            self._e = ">" if big_endian else "<"
        self._ifaces = []
        self._block(0x0A0D0D0A, self._section_header(comments))

    @staticmethod
    def comment_first_section(path: str | Path, comments: Sequence[str]) -> None:
        """Give the first section of the finished pcapng file ``path`` the
        ``shb_comment`` options ``comments`` (replacing its header, which must be
        one this writer wrote); the file is rewritten beside itself and renamed over,
        so a failure leaves the original whole. What a file says about itself is
        known only once it is written: the writer starts it with a plain header so
        that a live capture is readable from its first packet."""
        path = Path(path)
        with open(path, "rb") as f:
            head = f.read(12)
            if len(head) < 12 or head[:4] != b"\x0a\x0d\x0d\x0a":
                raise ValueError(f"{path}: not a pcapng file")
            e = "<" if head[8:12] == b"\x4d\x3c\x2b\x1a" else ">"
            (length,) = struct.unpack(e + "I", head[4:8])
            f.seek(length)
            tmp = path.with_name(path.name + ".tmp")
            try:
                with open(tmp, "wb") as out:
                    PcapngWriter(out, big_endian=e == ">", comments=comments)
                    while block := f.read(1 << 20):
                        out.write(block)
                tmp.replace(path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise

    def add_interface(
        self,
        linktype: int,
        *,
        snaplen: int = 0,
        tsresol: int | None = None,
        tsoffset: int | None = None,
    ) -> int:
        """An IDB; returns its interface id within the current section."""
        options = b""
        if tsresol is not None:
            options += self._option(9, bytes([tsresol]))
        if tsoffset is not None:
            options += self._option(14, struct.pack(self._e + "q", tsoffset))
        if options:
            options += self._option(0, b"")
        self._block(1, struct.pack(self._e + "HHI", linktype, 0, snaplen) + options)
        resol = 6 if tsresol is None else tsresol
        divisor = 2 ** (resol & 0x7F) if resol & 0x80 else 10**resol
        self._ifaces.append((divisor, snaplen))
        return len(self._ifaces) - 1

    def _units(self, interface: int, ts: float, tsoffset: int = 0) -> int:
        return round((ts - tsoffset) * self._ifaces[interface][0])

    def write(
        self,
        ts: float,
        data: bytes,
        *,
        interface: int = 0,
        orig_len: int | None = None,
        tsoffset: int = 0,
        comments: Sequence[str] = (),
    ) -> None:
        """An Enhanced Packet Block (``tsoffset``: the interface's if_tsoffset, if set;
        ``comments``: an ``opt_comment`` each, what Wireshark shows as the packet's
        comments, ``frame.comment``)."""
        units = self._units(interface, ts, tsoffset)
        head = struct.pack(
            self._e + "IIIII",
            interface,
            units >> 32,
            units & 0xFFFFFFFF,
            len(data),
            len(data) if orig_len is None else orig_len,
        )
        body = head + data + b"\0" * (-len(data) % 4)
        if comments:
            body += self._comments(comments) + self._option(0, b"")
        self._block(6, body)

    def write_simple(self, data: bytes, *, orig_len: int | None = None) -> None:
        """A Simple Packet Block (interface 0, no timestamp)."""
        self._block(
            3, struct.pack(self._e + "I", len(data) if orig_len is None else orig_len) + data
        )

    def write_obsolete(self, ts: float, data: bytes, *, interface: int = 0) -> None:
        """An obsolete Packet Block (type 2)."""
        units = self._units(interface, ts)
        head = struct.pack(
            self._e + "HHIIII", interface, 0, units >> 32, units & 0xFFFFFFFF, len(data), len(data)
        )
        self._block(2, head + data)

    def write_block(self, block_type: int, body: bytes) -> None:
        """Any other block (name resolution, statistics, custom...) as raw body bytes."""
        self._block(block_type, body)
