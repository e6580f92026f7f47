"""Live network capture: scapy as a byte source only, packets to the shared dissector.

:class:`PacketCapture` owns one Linux ``AF_PACKET`` socket opened through
scapy's ``conf.L2listen`` with the BPF filter compiled and attached in the
kernel, and a reader thread that takes raw frames with their kernel timestamps
(``SO_TIMESTAMPNS`` ancillary data) without any scapy dissection. The thread
hands each batch of packets to the hub with ``hub.submit``, so the dissector
(link layer -> IP -> TCP/UDP -> reassembly) runs in the hub's thread like every
other stage. Kernel drop counters (``PACKET_STATISTICS``) are read on demand.

On the loopback interface the kernel shows every packet twice (outgoing and
incoming); the outgoing copy is not queued (``PACKET_IGNORE_OUTGOING``) or
dropped by the reader on older kernels, as libpcap does.

scapy is imported only when a capture is opened: ``import mbmon`` stays light.
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from mbmon.model import Chunk, Event, EventKind, Stream, Transport
from mbmon.sources.base import BaseSource, SourceError, SourceMode
from mbmon.sources.pcapfile import CaptureConfig

if TYPE_CHECKING:
    from mbmon.hub import Hub

__all__ = [
    "CaptureSetupError",
    "CoreOutput",
    "InterfaceSource",
    "PacketCapture",
    "PacketDissector",
    "capture_filter",
    "interface_names",
    "list_interfaces",
    "open_dissector",
]

SOL_PACKET = 263
PACKET_STATISTICS = 6
PACKET_OUTGOING = 4
PACKET_IGNORE_OUTGOING = 23  # Linux 4.20+: the kernel does not queue outgoing copies at all
#: Linux ARPHRD_* hardware types -> pcap link types (what the dissector reads).
_LINKTYPE = {
    1: 1,  # Ethernet
    772: 1,  # loopback: an Ethernet header with zero addresses
    65534: 101,  # ARPHRD_NONE (tun): raw IP
    512: 101,  # PPP without header on AF_PACKET SOCK_RAW: raw IP
    776: 101,  # sit / IPv6-in-IPv4
    778: 101,  # GRE
    823: 101,  # ip6gre
}
#: Kernel receive buffer asked for (root may exceed rmem_max with SO_RCVBUFFORCE).
RCVBUF = 8 << 20
#: Packets taken from the socket before they are handed to the hub in one batch.
BATCH = 256
_SO_RCVBUFFORCE = 33
_SIOCGIFADDR = 0x8915


class CaptureSetupError(SourceError):
    """The capture cannot start (no such interface, no permission, bad filter): one line."""


class PacketDissector(Protocol):
    """The shared packet dissector as a live capture uses it (``mbmon.sources.dissect``)."""

    def packet_bytes(self, ts: float, linktype: int, data: bytes) -> list[Chunk | Event]: ...

    def tick(self, now: float) -> list[Chunk | Event]: ...

    def next_deadline(self) -> float | None: ...

    def finish(self, ts: float) -> list[Chunk | Event]: ...

    def stats(self) -> dict[str, int]: ...

    def detected(self) -> list[tuple[str, int, str, int]]: ...


def open_dissector(
    config: CaptureConfig,
    new_stream: Callable[[Transport, str, str], Stream],
    bus_name: str = "bus",
) -> PacketDissector:
    """The packet dissector of a live capture (the one :mod:`mbmon.sources.dissect`
    that files use too), its stream ids allocated by ``new_stream`` (the hub's);
    idle connections expire and holes are given up on the dissector's defaults."""
    from mbmon.sources.dissect import Dissector

    return Dissector(config, bus_name, new_stream=new_stream)


def capture_filter(config: CaptureConfig) -> str:
    """The default kernel filter: TCP and UDP on every Modbus port of ``config``;
    with port detection on (``config.detect``), every TCP packet and UDP on those
    ports (detection looks at TCP on any port)."""
    ports = sorted(config.tcp_ports | config.rtu_ports)
    if config.detect:
        return " or ".join(["tcp", *(f"udp port {port}" for port in ports)])
    return " or ".join(f"{proto} port {port}" for port in ports for proto in ("tcp", "udp"))


# --------------------------------------------------------------------------- interfaces


def interface_names() -> list[str]:
    """Names of the network interfaces of this host, in kernel index order."""
    try:
        return [name for _index, name in sorted(socket.if_nameindex())]
    except OSError:
        return []


def _ipv4(name: str) -> str | None:
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            req = struct.pack("256s", name.encode()[:15])
            res = fcntl.ioctl(s.fileno(), _SIOCGIFADDR, req)
            return socket.inet_ntoa(res[20:24])
    except OSError:
        return None


def list_interfaces() -> list[tuple[str, str]]:
    """``(name, description)`` per interface: link state and IPv4 address when known."""
    rows = []
    for name in interface_names():
        base = Path("/sys/class/net") / name
        try:
            state = (base / "operstate").read_text().strip()
        except OSError:
            state = "?"
        parts = [state]
        addr = _ipv4(name)
        if addr:
            parts.append(addr)
        rows.append((name, " ".join(parts)))
    return rows


# --------------------------------------------------------------------------- capture


@dataclass
class KernelStats:
    """Totals of the socket's ``PACKET_STATISTICS`` (the kernel resets them on each read)."""

    packets: int = 0
    drops: int = 0


class PacketCapture:
    """One AF_PACKET socket with a kernel BPF filter and the thread that reads it.

    ``deliver(batch)`` is called in the reader thread with a list of
    ``(ts, linktype, data)``; the command passes a function that submits the
    batch to the hub. :meth:`open` raises :class:`CaptureSetupError` with what the
    user must do; :meth:`stop` ends the thread and closes the socket.
    """

    def __init__(
        self,
        iface: str,
        bpf: str,
        deliver: Callable[[list[tuple[float, int, bytes]]], None],
        *,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.iface = iface
        self.bpf = bpf
        self._deliver = deliver
        self._on_error = on_error
        self._sock: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stats_lock = threading.Lock()
        self._kernel = KernelStats()
        self.linktype = 1
        self.loopback = False
        self.packets = 0  # packets handed on (outgoing loopback copies not counted)

    def open(self) -> None:
        """Open the socket and attach the filter; raise :class:`CaptureSetupError`."""
        names = interface_names()
        if self.iface not in names:
            raise CaptureSetupError(
                f"no interface {self.iface!r}; available: {', '.join(names) or 'none'}"
            )
        import logging

        logging.getLogger("scapy.runtime").setLevel(logging.ERROR)  # "Unable to guess type"
        logging.getLogger("scapy").setLevel(logging.ERROR)
        try:
            import scapy.arch  # noqa: F401  (sets conf.L2listen for this platform)
            from scapy.config import conf
            from scapy.error import Scapy_Exception
        except ImportError as exc:  # pragma: no cover - scapy is a dependency
            raise CaptureSetupError(f"live capture needs scapy ({exc})") from None
        try:
            sock = conf.L2listen(iface=self.iface, filter=self.bpf, promisc=False)
        except PermissionError:
            raise CaptureSetupError(
                "capturing needs root, or the capabilities CAP_NET_RAW and CAP_NET_ADMIN "
                f"on the Python binary (sudo setcap cap_net_raw,cap_net_admin=eip "
                f"{os.path.realpath(_python())})"
            ) from None
        except Scapy_Exception as exc:
            raise CaptureSetupError(f"bad capture filter {self.bpf!r}: {exc}") from None
        except OSError as exc:
            if exc.errno in (errno.EPERM, errno.EACCES):
                raise CaptureSetupError(
                    "capturing needs root, or CAP_NET_RAW and CAP_NET_ADMIN on the Python binary"
                ) from None
            if exc.errno in (errno.ENODEV, errno.ENXIO):
                raise CaptureSetupError(
                    f"no interface {self.iface!r}; available: {', '.join(interface_names())}"
                ) from None
            raise CaptureSetupError(f"cannot capture on {self.iface}: {exc}") from None
        self._sock = sock
        raw: socket.socket = sock.ins
        try:
            raw.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, RCVBUF)
        except OSError:
            try:
                raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
            except OSError:
                pass
        hatype = raw.getsockname()[3]
        self.linktype = _LINKTYPE.get(hatype, 1)
        self.loopback = hatype == 772
        if self.loopback:
            try:  # half the work, and the drop counter counts only packets that matter
                raw.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
            except OSError:
                pass  # an older kernel: the reader drops outgoing copies itself
        raw.setblocking(False)
        # The counters start from now: scapy opens the socket with a receive buffer of
        # 0 while it compiles and attaches the filter, so traffic in those milliseconds
        # is counted as drops that are not the capture's (read once, then forgotten).
        self.kernel_stats()
        with self._stats_lock:
            self._kernel = KernelStats()

    def start(self) -> None:
        """Start the reader thread (after :meth:`open`)."""
        self._thread = threading.Thread(target=self._run, name=f"sniff {self.iface}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop reading and close the socket (idempotent; any thread but the reader)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self.kernel_stats()
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None

    def kernel_stats(self) -> KernelStats:
        """Packets that passed the filter and packets the kernel dropped (totals so far)."""
        with self._stats_lock:
            sock = self._sock
            if sock is not None:
                try:
                    got = sock.ins.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8)
                    packets, drops = struct.unpack("II", got)
                    self._kernel.packets += packets
                    self._kernel.drops += drops
                except OSError:
                    pass
            return KernelStats(self._kernel.packets, self._kernel.drops)

    def _run(self) -> None:
        sock = self._sock
        raw: socket.socket = sock.ins
        recv = sock._recv_raw  # raw bytes, the address (packet type) and the kernel time
        stop = self._stop
        linktype = self.linktype
        loopback = self.loopback
        deliver = self._deliver
        fd = raw.fileno()
        receiver = _compiled_receiver(fd, linktype, loopback)
        while not stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], 0.2)
            except (OSError, ValueError):
                break
            if not ready:
                continue
            batch: list[tuple[float, int, bytes]] = []
            try:
                if receiver is not None:  # many packets per system call
                    while len(batch) < BATCH and receiver.read(batch, BATCH - len(batch)):
                        pass
                while receiver is None and len(batch) < BATCH:
                    data, addr, ts = recv(raw, 65535)
                    if loopback and addr[2] == PACKET_OUTGOING:
                        continue  # the same packet comes back in
                    if not data:
                        continue
                    batch.append((ts if ts is not None else time.time(), linktype, data))
            except BlockingIOError:
                pass
            except OSError as exc:
                if batch:
                    deliver(batch)
                if self._on_error is not None:
                    self._on_error(f"capture on {self.iface} failed: {exc}")
                break
            if batch:
                self.packets += len(batch)
                deliver(batch)


def _compiled_receiver(fd: int, linktype: int, loopback: bool) -> Any:
    """The compiled core's reader of the socket ``fd`` (``recvmmsg``: many packets per
    system call, the same bytes and times as scapy's ``_recv_raw`` one by one), or
    ``None`` in a pure run (``MBMON_NO_EXTENSIONS=1``, no compiler)."""
    from mbmon import core

    if not core.available():
        return None
    reader: Any = core._reader
    return reader._Receiver(fd, linktype, loopback)


def dissect_batch(
    dissector: PacketDissector, batch: Iterable[tuple[float, int, bytes]]
) -> list[Chunk | Event]:
    """Run a batch of captured packets through ``dissector`` (in the hub's thread)."""
    out: list[Chunk | Event] = []
    packet_bytes = dissector.packet_bytes
    for ts, linktype, data in batch:
        out.extend(packet_bytes(ts, linktype, data))
    return out


def _python() -> str:
    import sys

    return sys.executable


class InterfaceSource(BaseSource):
    """A network interface as a live source of the hub: a :class:`PacketCapture`
    reader thread submits packet batches, and the packet dissector (a hub ticker,
    its stream ids the hub's) runs them in the hub's thread.

    ``bpf`` is the kernel filter (default: :func:`capture_filter` of ``config``).
    A capture that fails while running puts a NOTICE and stops the run.
    """

    mode: SourceMode = "live"

    def __init__(
        self,
        iface: str,
        config: CaptureConfig,
        bpf: str | None = None,
        *,
        core: CoreOutput | None = None,
    ) -> None:
        super().__init__()
        self.name = iface
        self.config = config
        self.bpf = bpf or capture_filter(config)
        self.capture: PacketCapture | None = None
        self.dissector: PacketDissector | None = None
        #: with ``core``: the compiled core's stage (:class:`mbmon.core.live.LiveCore`)
        self.core = core
        self.live: Any = None

    def open(self, hub: Hub) -> None:
        """Open the socket with its filter (:class:`CaptureSetupError` when it cannot)
        and register the dissector."""
        super().open(hub)
        dissector = self.dissector = open_dissector(self.config, hub.new_stream, self.name)
        stage: Any = dissector
        if self.core is None:

            def deliver(batch: list[tuple[float, int, bytes]]) -> None:
                hub.submit(lambda: dissect_batch(dissector, batch))

        else:
            stage = self.live = self.core.stage(self.config, dissector, hub)
            packets = self.live.packets

            def deliver(batch: list[tuple[float, int, bytes]]) -> None:
                hub.submit(lambda: packets(batch))

        def failed(message: str) -> None:
            hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": message}))
            hub.stop()

        capture = PacketCapture(self.name, self.bpf, deliver, on_error=failed)
        capture.open()
        self.capture = capture
        hub.add_ticker(stage)

    def start(self) -> None:
        """Start the reader thread."""
        if self.capture is not None:
            self.capture.start()

    def stop(self) -> None:
        """Stop reading and close the socket (idempotent)."""
        if self.capture is not None:
            self.capture.stop()

    def describe(self) -> str:
        """The kernel filter, for the banner."""
        return f"filter: {self.bpf}"

    def stats(self) -> dict[str, Any]:
        """Open connections (picked up mid-stream too) and kernel drops, for the screen."""
        if self.capture is None or self.dissector is None:
            return {}
        return {
            "open connections": self._dissector_stats()["open_connections"],
            "kernel drops": self.capture.kernel_stats().drops,
        }

    def closing(self, ts: float) -> list[Event]:
        """A STATS event with the kernel's counters: a log says by itself whether the
        capture was complete."""
        capture = self.capture
        if capture is None:
            return []
        k = capture.kernel_stats()
        info = {
            "interface": capture.iface,
            "packets": capture.packets,
            "kernel_packets": k.packets,
            "kernel_drops": k.drops,
            "complete": k.drops == 0,
        }
        return [Event(ts, None, EventKind.STATS, info)]

    def summary(self) -> list[str]:
        """Packets captured, the kernel's counters, and what the dissector made of them."""
        capture = self.capture
        if capture is None:
            return []
        k = capture.kernel_stats()
        lines = [
            f"{capture.packets} packets captured; kernel: {k.packets} matched the filter, "
            f"{k.drops} dropped" + (" (capture INCOMPLETE)" if k.drops else "")
        ]
        if self.dissector is not None:
            s = self._dissector_stats()
            lines.append(
                f"{s.get('modbus_packets', 0)} Modbus packets, {s.get('streams', 0)} streams, "
                f"{s.get('gaps', 0)} TCP gaps"
            )
        if self.live is not None:
            handed = self.live.handed
            lines.append(
                "core: the compiled core"
                + ("" if handed is None else f", then the Python pipeline ({handed})")
            )
        return lines

    def detected(self) -> list[tuple[str, int, str, int]]:
        """What port detection found (see ``Dissector.detected``)."""
        return self.dissector.detected() if self.dissector is not None else []

    def _dissector_stats(self) -> dict[str, int]:
        """The dissector's figures (the core's share included when it runs)."""
        if self.live is not None:
            got: dict[str, int] = self.live.stats()
            return got
        assert self.dissector is not None
        return self.dissector.stats()


@dataclass
class CoreOutput:
    """How ``sniff`` runs on the compiled core (:mod:`mbmon.core.live`): the view and
    JSON choice of its lines, the pairing timeout, and ``write``/``flush`` of
    stdout's bytes."""

    view: Any
    as_json: bool
    timeout: float
    write: Callable[[bytes], Any]
    flush: Callable[[], Any]

    def stage(self, config: CaptureConfig, dissector: Any, hub: Hub) -> Any:
        """The core's hub stage for ``config``'s ports, the reference's ``dissector``
        and ``hub``'s pipeline waiting behind it."""
        from mbmon.core.live import LiveCore

        return LiveCore(
            ports=config.tcp_ports,
            timeout=self.timeout,
            view=self.view,
            as_json=self.as_json,
            write=self.write,
            flush=self.flush,
            new_stream=hub.new_stream,
            dissector=dissector,
            pipeline=hub.pipeline,
        )
