"""Regenerate the project's own captures from real traffic on this machine.

    sudo python captures/make_captures.py                 # every capture
    sudo python captures/make_captures.py --only tcp      # hrss_ptp.pcap only
    sudo python captures/make_captures.py --only rtu      # hrss_rtu.pcap + hrss_rtu.bin only
    sudo python captures/make_captures.py --only demo --only fail   # (repeatable)

``--only``: tcp, rtu (the scripted server below), demo, functions, exceptions,
fail, sim-rtu (mbmon's own simulator, ``mbmon.sim``; see "captures of sim").

What this script owns:

* an HRSS-like Modbus server (pymodbus 3.16 ``SimDevice`` with an ``action``
  hook) that keeps the register map of chapter 5.3.3 of the HIWIN manual and a
  tiny motion state machine: writing R200 = 1 after the PTP parameters starts a
  "motion" that runs for a fixed number of status polls, then reports IR200 = 1
  (success) and IR524 = 1 (idle); reads outside the map answer exception 02;
* the client session an HRSS client program runs (manual §5.3.3.7 Example 3,
  Table 46, and the §5.4.5.2 program): speed, SO/SI signals, DO coils, PTP
  parameters with FC10, R200 handshake, status polling, one bad read;
* the recorders: ``tcpdump -i lo`` for Modbus/TCP, and for RTU a relay between
  two ``socat`` pty pairs that forwards every byte both ways and writes each
  read, timestamped, as one link-type-147 record and into a raw bus dump.

and, for the captures of ``sim``: ``mbmon.sim`` on 127.0.0.1:502 (or on a pty
for RTU) with raw-socket sessions (function codes, exceptions, a failing
command), the demo's client through ``mbmon proxy -w demo.pcap``, and the
§5.4.5.2 program over RTU.

Content of hrss_* is deterministic (polls are counted, not timed); the sim's
motions are timed, so the number of IR524 polls in demo.pcap and sim_rtu.*
varies by one or two. Timestamps, TCP ports and sequence numbers differ from
run to run. Needs root (port 502, tcpdump), tcpdump, socat and pymodbus >= 3.16.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from mbmon.semantics.words import split_i32, u16  # noqa: E402

UNIT = 1
TCP_HOST = "127.0.0.1"
TCP_PORT = 502
RTU_BAUD = 115200
MOTION_POLLS = 4  # status polls during which the robot reports Running

# Input registers (Table 14)
IR_SPEED = 100
IR_CMD_CODE = 101
IR_QUEUE = 102
IR_STATUS = 200
IR_ACTION = 201
IR_JOINTS = 300
IR_MOTION = 524
# Holding registers (Table 15 / Table 17)
HR_SPEED = 100
HR_ENABLE = 200
HR_PARAMS = 201  # R201..R251

START_POSE = (0, 0, 0, 0, -90_000, 0)  # 0.001 degree, A5 = -90 degree
PTP_TARGET = (90_000, 0, 0, 0, 0, 0)  # PTP {A1 90, A2 0, ..., A6 0}


def ptp_parameters() -> list[int]:
    """R201..R226 for PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2].

    Exactly Table 46: command 0, point type 0 (joints), A1..A6 as low/high
    words, speed 50, acceleration 100, tool 1, base 2, no external axes, custom
    command code 0 (R226).
    """
    regs = [0, 0]  # R201 command number PTP, R202 point type joints
    for value in PTP_TARGET:
        low, high = split_i32(value)
        regs += [u16(low), u16(high)]
    regs += [50, 100, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0]  # R215..R226
    assert len(regs) == 26 and regs[2:4] == [24464, 1]
    return regs


@dataclass
class HrssRobot:
    """The server-side robot: the register blocks and the motion state machine.

    pymodbus calls :meth:`action` for every access, before a write is applied
    and before a read's values are returned, with the block's registers to
    modify in place. Input registers are refreshed from this state on each
    FC04 read; the motion clock advances on each read of IR200.
    """

    joints: list[int] = field(default_factory=lambda: list(START_POSE))
    params: list[int] = field(default_factory=lambda: [0] * 51)  # R201..R251
    status: int = 0  # IR200: 0 ready, 1 success, 2 fail
    motion: int = 1  # IR524: 1 idle, 2 running
    speed: int = 100
    start: tuple[int, ...] = ()
    target: tuple[int, ...] = ()
    polls: int = 0

    def device(self) -> SimDevice:
        """The register map (Tables 12-15); addresses outside it are invalid -> exception 02."""
        bits, regs = DataType.BITS, DataType.REGISTERS
        off = [False] * 256  # bit blocks take a list (pymodbus 3.16 counts count= twice)
        coils = [
            SimData(0, values=off, datatype=bits),  # SI1..SI256
            SimData(300, values=off, datatype=bits),
        ]  # DO[1..256]
        so = [False, False, False, True] + [False] * 252  # SO4 Ready
        dinputs = [
            SimData(0, values=so, datatype=bits),  # SO1..SO256 (Table 45)
            SimData(300, values=off, datatype=bits),
        ]  # DI[1..256]
        holding = [
            SimData(0, count=32, values=0, datatype=regs),  # SRR
            SimData(HR_SPEED, values=100, datatype=regs),
            SimData(HR_ENABLE, count=52, values=0, datatype=regs),  # R200..R251
            SimData(300, count=40, values=0, datatype=regs),
        ]  # timers
        inputs = [
            SimData(0, count=32, values=0, datatype=regs),  # SRW
            SimData(IR_SPEED, count=3, values=0, datatype=regs),
            SimData(IR_STATUS, count=52, values=0, datatype=regs),
            SimData(IR_JOINTS, count=12, values=0, datatype=regs),
            SimData(400, count=12, values=0, datatype=regs),
            SimData(500, count=4, values=0, datatype=regs),
            SimData(520, count=5, values=0, datatype=regs),
        ]
        return SimDevice(UNIT, simdata=(coils, dinputs, holding, inputs), action=self.action)

    async def action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """React to one access: writes change the state, FC04 reads see it."""
        if fc in (6, 16) and values is not None:
            self._written(address, [int(v) for v in values])
        elif fc == 4:
            if address <= IR_STATUS < address + count:
                self._tick()
            self._publish(start, registers)
        return None

    def _written(self, address: int, values: list[int]) -> None:
        for i, value in enumerate(values):
            reg = address + i
            if reg == HR_SPEED:
                self.speed = value
            elif HR_PARAMS <= reg < HR_PARAMS + 51:
                self.params[reg - HR_PARAMS] = value
            elif reg == HR_ENABLE and value == 1 and self.motion == 1:
                self._start_motion()
            elif reg == HR_ENABLE and value == 0 and self.motion == 1:
                self.status = 0  # handshake back to ready

    def _start_motion(self) -> None:
        p = self.params
        target = []
        for axis in range(6):
            low, high = p[2 + 2 * axis], p[3 + 2 * axis]
            v = (high << 16) | low
            target.append(v - (1 << 32) if v & 0x8000_0000 else v)
        self.start, self.target = tuple(self.joints), tuple(target)
        self.status, self.motion, self.polls = 0, 2, 0

    def _tick(self) -> None:
        if self.motion != 2:
            return
        self.polls += 1
        if self.polls > MOTION_POLLS:
            self.joints = list(self.target)
            self.status, self.motion = 1, 1
            return
        self.joints = [
            s + (t - s) * self.polls // (MOTION_POLLS + 1)
            for s, t in zip(self.start, self.target, strict=True)
        ]

    def _publish(self, start: int, registers: list[int]) -> None:
        running = self.motion == 2

        def put(reg: int, value: int) -> None:
            registers[reg - start] = u16(value)

        put(IR_SPEED, self.speed)
        put(IR_CMD_CODE, self.params[25] if running else 0)  # R226 custom command code
        put(IR_QUEUE, 1 if running else 0)
        put(IR_STATUS, self.status)
        put(IR_ACTION, self.params[0])
        for axis, value in enumerate(self.joints):
            low, high = split_i32(value)
            put(IR_JOINTS + 2 * axis, low)
            put(IR_JOINTS + 2 * axis + 1, high)
        put(IR_MOTION, self.motion)
        put(522, 1)  # excited


async def hrss_session(client: Any, log: list[str]) -> None:
    """What an HRSS client program does (§5.4.5.2 program + Table 46 PTP), one request at a time."""

    def check(rr: Any, what: str) -> Any:
        if rr.isError():
            raise RuntimeError(f"{what}: unexpected error {rr}")
        log.append(what)
        return rr

    def expect(got: object, want: object, what: str) -> None:
        if got != want:
            raise RuntimeError(f"{what}: got {got}, expected {want}")

    rr = check(
        await client.read_input_registers(IR_SPEED, count=1, device_id=UNIT), "FC04 IR100 speed"
    )
    expect(rr.registers, [100], "IR100")
    check(await client.write_register(HR_SPEED, 90, device_id=UNIT), "FC06 R100 = 90")
    rr = check(await client.read_discrete_inputs(0, count=8, device_id=UNIT), "FC02 SO1..SO8")
    expect([int(b) for b in rr.bits[:8]], [0, 0, 0, 1, 0, 0, 0, 0], "SO1..SO8")
    check(await client.write_coil(0, True, device_id=UNIT), "FC05 SI1 Start ON")
    check(
        await client.write_coils(300, [True, True, False, False, True], device_id=UNIT),
        "FC0F DO[1..5]",
    )
    rr = check(await client.read_coils(0, count=8, device_id=UNIT), "FC01 SI1..SI8")
    expect([int(b) for b in rr.bits[:8]], [1, 0, 0, 0, 0, 0, 0, 0], "SI1..SI8")
    check(await client.write_registers(HR_ENABLE, [0], device_id=UNIT), "FC10 R200 = 0")
    check(
        await client.write_registers(HR_PARAMS, ptp_parameters(), device_id=UNIT),
        "FC10 R201..R226 PTP",
    )
    rr = check(
        await client.read_holding_registers(HR_ENABLE, count=2, device_id=UNIT), "FC03 R200..R201"
    )
    expect(rr.registers, [0, 0], "R200..R201")
    check(await client.write_register(HR_ENABLE, 1, device_id=UNIT), "FC06 R200 = 1")
    for _ in range(MOTION_POLLS + 3):
        status = check(
            await client.read_input_registers(IR_STATUS, count=1, device_id=UNIT),
            "FC04 IR200 status",
        ).registers[0]
        motion = check(
            await client.read_input_registers(IR_MOTION, count=1, device_id=UNIT),
            "FC04 IR524 motion",
        ).registers[0]
        joints = check(
            await client.read_input_registers(IR_JOINTS, count=12, device_id=UNIT),
            "FC04 IR300..IR311 joints",
        ).registers
        if status != 0 and motion == 1:
            break
        await asyncio.sleep(0.1)  # WAIT SEC 0.1 of the manual's polling loop
    else:
        raise RuntimeError("the motion never finished")
    expect(status, 1, "IR200 command status")
    expect(joints, [24464, 1] + [0] * 10, "IR300..IR311 after the PTP")
    check(await client.write_register(HR_ENABLE, 0, device_id=UNIT), "FC06 R200 = 0")
    rr = await client.read_holding_registers(1000, count=2, device_id=UNIT)
    if not rr.isError() or getattr(rr, "exception_code", None) != 2:
        raise RuntimeError(f"read of R1000 should answer exception 02, got {rr}")
    log.append("FC03 R1000 -> exception 02")
    check(await client.write_coil(0, False, device_id=UNIT), "FC05 SI1 Start OFF")


# --------------------------------------------------------------------------- pcap writing


def pcap_header(linktype: int) -> bytes:
    """Classic little-endian microsecond pcap global header."""
    return struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, linktype)


def pcap_record(ts: float, data: bytes) -> bytes:
    """One pcap record header + data."""
    sec = int(ts)
    usec = round((ts - sec) * 1e6)
    if usec >= 1_000_000:
        sec, usec = sec + 1, usec - 1_000_000
    return struct.pack("<IIII", sec, usec, len(data), len(data)) + data


# --------------------------------------------------------------------------- TCP capture


def run(cmd: Sequence[str]) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True).stdout


async def capture_tcp(out: Path) -> list[str]:
    """Serve the robot on 127.0.0.1:502, record lo with tcpdump, run one client session."""
    robot = HrssRobot()
    server = ModbusTcpServer(robot.device(), address=(TCP_HOST, TCP_PORT))
    await server.serve_forever(background=True)
    for _ in range(100):  # wait until the port accepts connections
        try:
            _, w = await asyncio.open_connection(TCP_HOST, TCP_PORT)
        except OSError:
            await asyncio.sleep(0.05)
            continue
        w.close()
        await w.wait_closed()
        break
    else:
        raise RuntimeError("server did not start listening")
    await asyncio.sleep(0.3)  # let the probe connection's teardown finish before recording
    tmp = out.with_suffix(".tmp")
    dump = subprocess.Popen(
        ["tcpdump", "-i", "lo", "-w", str(tmp), "-U", "-n", f"tcp port {TCP_PORT}"],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert dump.stderr is not None
    line = dump.stderr.readline()
    if "listening on" not in line:
        dump.kill()
        raise RuntimeError(f"tcpdump did not start: {line.strip()}")
    await asyncio.sleep(0.5)
    log: list[str] = []
    client = AsyncModbusTcpClient(TCP_HOST, port=TCP_PORT, retries=0)
    try:
        if not await client.connect():
            raise RuntimeError("client could not connect")
        await hrss_session(client, log)
    finally:
        client.close()
        await asyncio.sleep(0.5)  # FIN/ACK exchange reaches the capture
        dump.send_signal(signal.SIGINT)
        _, err = dump.communicate(timeout=10)
        await server.shutdown()
    sys.stderr.write(err)
    out.unlink(missing_ok=True)
    out.write_bytes(tmp.read_bytes())  # tcpdump wrote tmp as its own user; keep ours
    tmp.unlink()
    return log


# --------------------------------------------------------------------------- RTU capture


def socat_pair() -> tuple[subprocess.Popen[str], str, str]:
    """Start ``socat -d -d pty,raw,echo=0 pty,raw,echo=0`` and return it with its two pty paths."""
    proc = subprocess.Popen(
        ["socat", "-d", "-d", "pty,raw,echo=0", "pty,raw,echo=0"], stderr=subprocess.PIPE, text=True
    )
    assert proc.stderr is not None
    ptys: list[str] = []
    while len(ptys) < 2:
        line = proc.stderr.readline()
        if not line:
            raise RuntimeError("socat exited before opening its ptys")
        m = re.search(r"PTY is (\S+)", line)
        if m:
            ptys.append(m.group(1))
    # keep draining stderr so socat never blocks on it
    threading.Thread(target=proc.stderr.read, daemon=True).start()
    return proc, ptys[0], ptys[1]


class BusTap:
    """Forward bytes between two ptys both ways and record every read, like an RS485 sniffer."""

    def __init__(self, a: str, b: str) -> None:
        self.fds = [os.open(p, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK) for p in (a, b)]
        self.records: list[tuple[float, bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> BusTap:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for fd in self.fds:
            os.close(fd)

    def _run(self) -> None:
        a, b = self.fds
        while not self._stop.is_set():
            ready, _, _ = select.select(self.fds, [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                if not data:
                    continue
                self.records.append((time.time(), data))
                other = b if fd == a else a
                view = memoryview(data)
                while view:
                    try:
                        n = os.write(other, view)
                    except BlockingIOError:
                        select.select([], [other], [], 0.1)
                        continue
                    view = view[n:]


async def capture_rtu(pcap: Path, raw: Path) -> list[str]:
    """RTU server and client on two pty pairs joined by a recording relay."""
    client_pair = socat_pair()
    server_pair = socat_pair()
    procs = [client_pair[0], server_pair[0]]
    try:
        client_pty, tap_a = client_pair[1], client_pair[2]
        tap_b, server_pty = server_pair[1], server_pair[2]
        robot = HrssRobot()
        server = ModbusSerialServer(
            robot.device(), framer=FramerType.RTU, port=server_pty, baudrate=RTU_BAUD
        )
        with BusTap(tap_a, tap_b) as tap:
            await server.serve_forever(background=True)
            await asyncio.sleep(0.5)
            client = AsyncModbusSerialClient(
                client_pty, framer=FramerType.RTU, baudrate=RTU_BAUD, retries=0
            )
            log: list[str] = []
            try:
                if not await client.connect():
                    raise RuntimeError("serial client could not open its pty")
                await hrss_session(client, log)
            finally:
                client.close()
                await asyncio.sleep(0.3)
                await server.shutdown()
        records = tap.records
    finally:
        for p in procs:
            p.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=5)
    with pcap.open("wb") as f:
        f.write(pcap_header(147))
        for ts, data in records:
            f.write(pcap_record(ts, data))
    raw.write_bytes(b"".join(data for _, data in records))
    return log


# --------------------------------------------------------------------------- captures of `sim`
#
# These record mbmon's own simulator (mbmon.sim, the same server `mbmon sim` and
# `mbmon demo` run) on 127.0.0.1:502. Requests are written as raw PDUs on a
# plain socket (transaction ids 1..N), so the bytes are exactly the ones listed
# here and in captures/README.md; the answers are checked as the session runs.

#: (what, unit, request PDU, the answer the sim must give) of the function-code session.
FUNCTIONS: list[tuple[str, int, str, str | None]] = [
    ("FC01 read coils 0..7 (SI1..SI8)", 1, "01 00 00 00 08", "01 01 00"),
    ("FC02 read discrete inputs 300..307 (DI[1..8])", 1, "02 01 2C 00 08", "02 01 05"),
    ("FC03 read R100 (set speed)", 1, "03 00 64 00 01", "03 02 00 64"),
    ("FC04 read IR100 (speed %)", 1, "04 00 64 00 01", "04 02 00 64"),
    ("FC05 write coil 300 (DO[1]) ON", 1, "05 01 2C FF 00", "05 01 2C FF 00"),
    ("FC06 write R100 = 90", 1, "06 00 64 00 5A", "06 00 64 00 5A"),
    (
        "FC0F write coils 300..304 (DO[1..5]) = 1 1 0 0 1",
        1,
        "0F 01 2C 00 05 01 13",
        "0F 01 2C 00 05",
    ),
    ("FC10 write R0..R1 (SRR) = 1, 2", 1, "10 00 00 00 02 04 00 01 00 02", "10 00 00 00 02"),
    ("FC01 read coils 300..304 back", 1, "01 01 2C 00 05", "01 01 13"),
    ("FC03 read R0..R1 back", 1, "03 00 00 00 02", "03 04 00 01 00 02"),
    ("FC04 read IR100 after the write", 1, "04 00 64 00 01", "04 02 00 5A"),
    # not in the manual's Table 10: exception 01 Illegal Function
    ("FC07 read exception status", 1, "07", "87 01"),
    ("FC08 diagnostics, return query data", 1, "08 00 00 12 34", "88 01"),
    ("FC0B get comm event counter", 1, "0B", "8B 01"),
    ("FC0C get comm event log", 1, "0C", "8C 01"),
    ("FC11 report server id", 1, "11", "91 01"),
    ("FC15 write file record", 1, "15 09 06 00 01 00 00 00 01 00 00", "95 01"),
    ("FC16 mask write R100", 1, "16 00 64 FF 00 00 00", "96 01"),
    ("FC17 read/write R100", 1, "17 00 64 00 01 00 64 00 01 02 00 5A", "97 01"),
    ("FC18 read FIFO queue", 1, "18 00 64", "98 01"),
    ("FC2B/0E read device identification", 1, "2B 0E 01 00", "AB 01"),
]

#: The exception session: each kind of refusal the sim gives, a good read after each.
EXCEPTIONS: list[tuple[str, int, str, str | None]] = [
    ("FC2B not served: exception 01", 1, "2B 0E 01 00", "AB 01"),
    ("FC04 IR300..IR411 crosses the gap 312..399: exception 02", 1, "04 01 2C 00 70", "84 02"),
    ("FC04 IR300..IR311 (A1..A6) is fine", 1, "04 01 2C 00 0C", None),
    ("FC01 coils 256..263 (between SI256 and DO[1]): exception 02", 1, "01 01 00 00 08", "81 02"),
    ("FC06 R50 (not in the map): exception 02", 1, "06 00 32 00 01", "86 02"),
    ("FC10 R1950..R1951 (after PR[50]): exception 02", 1, "10 07 9E 00 02 04 00 00 00 00", "90 02"),
    ("FC06 R100 = 0 (speed 1..100): exception 03", 1, "06 00 64 00 00", "86 03"),
    ("FC10 R100 = 101: exception 03", 1, "10 00 64 00 01 02 00 65", "90 03"),
    ("FC06 R200 = 2 (0..1): exception 03", 1, "06 00 C8 00 02", "86 03"),
    ("FC04 IR100 for unit 2 (the sim is unit 1): exception 0B", 2, "04 00 64 00 01", "84 0B"),
    ("FC04 IR100 for unit 1 still answers", 1, "04 00 64 00 01", "04 02 00 64"),
]


def _words(values: Sequence[int]) -> str:
    return " ".join(f"{v & 0xFFFF:04X}" for v in values)


def _execute(params: Sequence[int]) -> list[str]:
    """R200 = 0, parameters from R201 (FC10), R200 = 1: the handshake of §5.3.3.5."""
    n = len(params)
    return ["06 00 C8 00 00", f"10 00 C9 00 {n:02X} {2 * n:02X} {_words(params)}", "06 00 C8 00 01"]


#: PTP {A1 90} of Table 46 at Vel=250 % (R215 = 250, outside 1..200).
PTP_250 = [0, 0, 24464, 1] + [0] * 10 + [250, 100, 1, 2] + [0] * 8

#: The failing-command session: (what, PDU, answer) with ``None`` for an answer not fixed here.
FAIL: list[tuple[str, int, str, str | None]] = [
    *[
        (f"PTP Vel=250%: {w}", 1, pdu, None)
        for w, pdu in zip(("R200 = 0", "R201..R226", "R200 = 1"), _execute(PTP_250), strict=True)
    ],
    ("IR200..IR201: status 2 (fail), command 0 (PTP)", 1, "04 00 C8 00 02", "04 04 00 02 00 00"),
    ("IR524: the robot did not move (1 Idle)", 1, "04 02 0C 00 01", "04 02 00 01"),
    *[
        (f"Get PR[0]: {w}", 1, pdu, None)
        for w, pdu in zip(("R200 = 0", "R201..R202", "R200 = 1"), _execute([200, 0]), strict=True)
    ],
    (
        "IR200..IR201: status 2 (PR 0 outside 1..4000), command 200",
        1,
        "04 00 C8 00 02",
        "04 04 00 02 00 C8",
    ),
    ("R200 = 1 again without R200 = 0: nothing executes", 1, "06 00 C8 00 01", "06 00 C8 00 01"),
    *[
        (f"Set Current TOOL[3]: {w}", 1, pdu, None)
        for w, pdu in zip(("R200 = 0", "R201..R202", "R200 = 1"), _execute([103, 3]), strict=True)
    ],
    ("IR200..IR201: status 1 (success), command 103", 1, "04 00 C8 00 02", "04 04 00 01 00 67"),
    ("R200 = 0", 1, "06 00 C8 00 00", "06 00 C8 00 00"),
]


class RawClient:
    """A Modbus/TCP client on a plain socket: exactly the PDUs given, tids 1, 2, 3 ..."""

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.create_connection((host, port), timeout=5)
        self.tid = 0

    def ask(self, unit: int, pdu_hex: str) -> str:
        self.tid += 1
        pdu = bytes.fromhex(pdu_hex)
        self.sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, unit) + pdu)
        head = self._read(7)
        tid, proto, length, got_unit = struct.unpack(">HHHB", head)
        if (tid, proto, got_unit) != (self.tid, 0, unit):
            raise RuntimeError(f"answer to tid {self.tid}: header {head.hex(' ')}")
        return self._read(length - 1).hex(" ").upper()

    def _read(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            more = self.sock.recv(n - len(data))
            if not more:
                raise RuntimeError("the server closed the connection")
            data += more
        return data

    def close(self) -> None:
        self.sock.close()


def run_raw(session: Sequence[tuple[str, int, str, str | None]], port: int) -> list[str]:
    """Send every request of ``session``, one at a time; check the fixed answers."""
    client = RawClient(TCP_HOST, port)
    log: list[str] = []
    try:
        for what, unit, pdu, want in session:
            got = client.ask(unit, pdu)
            if want is not None and got != want:
                raise RuntimeError(f"{what}: answer {got}, expected {want}")
            log.append(f"{what}: {pdu} -> {got}")
    finally:
        client.close()
    return log


@contextlib.contextmanager
def tcpdump_lo(out: Path, port: int) -> Any:
    """Record Modbus/TCP on ``lo`` port ``port`` into ``out`` while the block runs."""
    tmp = out.with_suffix(".tmp")
    dump = subprocess.Popen(
        ["tcpdump", "-i", "lo", "--immediate-mode", "-w", str(tmp), "-U", "-n", f"tcp port {port}"],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert dump.stderr is not None
    line = dump.stderr.readline()
    if "listening on" not in line:
        dump.kill()
        raise RuntimeError(f"tcpdump did not start: {line.strip()}")
    time.sleep(0.5)
    try:
        yield
    finally:
        time.sleep(1.0)  # FIN/ACK exchange reaches the capture
        dump.send_signal(signal.SIGINT)
        _, err = dump.communicate(timeout=10)
        sys.stderr.write(err)
    out.unlink(missing_ok=True)
    out.write_bytes(tmp.read_bytes())  # tcpdump wrote tmp as its own user; keep ours
    tmp.unlink()


Session = Sequence[tuple[str, int, str, str | None]]


def capture_sim_session(out: Path, session: Session) -> list[str]:
    """``mbmon.sim`` on 127.0.0.1:502, tcpdump on ``lo``, one raw client session."""
    from mbmon.sim.server import SimServer

    with SimServer(host=TCP_HOST, port=TCP_PORT), tcpdump_lo(out, TCP_PORT):
        return run_raw(session, TCP_PORT)


def _mbmon(*args: str, **kw: Any) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(HERE.parent)}
    return subprocess.Popen([sys.executable, "-m", "mbmon", *args], env=env, text=True, **kw)


def capture_demo(out: Path) -> list[str]:
    """The demo's traffic: ``mbmon.sim`` on 127.0.0.1:502, ``mbmon proxy`` on 1502 with the
    demo's guard writing ``out`` (its pcap sink), and the demo's own client through it."""
    import threading as _threading

    from mbmon.commands.demo import GUARD_SPEC, DemoClient
    from mbmon.sim.server import SimServer

    out.unlink(missing_ok=True)
    log: list[str] = []
    with SimServer(host=TCP_HOST, port=TCP_PORT):
        proxy = _mbmon(
            "proxy",
            "--upstream",
            f"{TCP_HOST}:{TCP_PORT}",
            "--listen",
            f"{TCP_HOST}:1502",
            "--deny-write",
            GUARD_SPEC,
            "--profile",
            "hrss",
            "-q",
            "-w",
            str(out),
            stderr=subprocess.PIPE,
        )
        assert proxy.stderr is not None
        line = proxy.stderr.readline()
        if "listening on" not in line:
            proxy.kill()
            raise RuntimeError(f"mbmon proxy did not start: {line.strip()}")
        try:
            client = DemoClient(TCP_HOST, 1502, log.append, fast=True, stop=_threading.Event())
            client.run()
            if client.error is not None:
                raise RuntimeError(f"demo client: {client.error}")
            log.append(f"{client.requests} requests, SI1 write refused with {client.refused}")
            time.sleep(0.3)
        finally:
            proxy.send_signal(signal.SIGINT)
            _, err = proxy.communicate(timeout=20)
    if proxy.returncode != 0:
        raise RuntimeError(f"mbmon proxy failed: {err}")
    return log


def capture_sim_rtu(pcap: Path, raw: Path) -> list[str]:
    """``mbmon.sim`` serving RTU on a pty, the §5.4.5.2 program on another, a recording relay."""
    from pymodbus.client import ModbusSerialClient

    from mbmon.sim.program import run_program
    from mbmon.sim.server import SimServer

    client_pair = socat_pair()
    server_pair = socat_pair()
    procs = [client_pair[0], server_pair[0]]
    log: list[str] = []
    try:
        client_pty, tap_a = client_pair[1], client_pair[2]
        tap_b, server_pty = server_pair[1], server_pair[2]
        with BusTap(tap_a, tap_b) as tap:
            with SimServer(serial=server_pty, baudrate=RTU_BAUD, unit=UNIT):
                time.sleep(0.3)
                client = ModbusSerialClient(
                    client_pty, framer=FramerType.RTU, baudrate=RTU_BAUD, timeout=2, retries=0
                )
                if not client.connect():
                    raise RuntimeError("serial client could not open its pty")
                try:
                    result = run_program(
                        client=client, extras=False, on_step=lambda st: log.append(st.line)
                    )
                finally:
                    client.close()
                if result.joints[0] != 90:
                    raise RuntimeError(f"A1 ended at {result.joints[0]}, not 90")
                time.sleep(0.2)
        records = tap.records
    finally:
        for p in procs:
            p.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=5)
    with pcap.open("wb") as f:
        f.write(pcap_header(147))
        for ts, data in records:
            f.write(pcap_record(ts, data))
    raw.write_bytes(b"".join(data for _, data in records))
    return log


# --------------------------------------------------------------------------- main


ONLY = ("tcp", "rtu", "demo", "functions", "exceptions", "fail", "sim-rtu")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--only", choices=ONLY, action="append", help="make only these (repeatable; default: all)"
    )
    ap.add_argument("--out", type=Path, default=HERE)
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        print(
            "needs root (port 502 and tcpdump): sudo python captures/make_captures.py",
            file=sys.stderr,
        )
        return 2
    for tool in ("tcpdump", "socat"):
        if shutil.which(tool) is None:
            print(f"{tool} is not installed", file=sys.stderr)
            return 2
    wanted = set(args.only or ONLY)
    if "tcp" in wanted:
        out = args.out / "hrss_ptp.pcap"
        log = asyncio.run(capture_tcp(out))
        print(f"{out}: {len(log)} transactions ({out.stat().st_size} bytes)")
    if "rtu" in wanted:
        pcap, raw = args.out / "hrss_rtu.pcap", args.out / "hrss_rtu.bin"
        log = asyncio.run(capture_rtu(pcap, raw))
        print(f"{pcap}, {raw}: {len(log)} transactions ({raw.stat().st_size} bus bytes)")
    for name, file, session in (
        ("functions", "sim_functions.pcap", FUNCTIONS),
        ("exceptions", "sim_exceptions.pcap", EXCEPTIONS),
        ("fail", "sim_fail.pcap", FAIL),
    ):
        if name in wanted:
            out = args.out / file
            log = capture_sim_session(out, session)
            print(f"{out}: {len(log)} transactions ({out.stat().st_size} bytes)")
    if "demo" in wanted:
        out = args.out / "demo.pcap"
        log = capture_demo(out)
        print(f"{out}: {log[-1]} ({out.stat().st_size} bytes)")
    if "sim-rtu" in wanted:
        pcap, raw = args.out / "sim_rtu.pcap", args.out / "sim_rtu.bin"
        log = capture_sim_rtu(pcap, raw)
        print(f"{pcap}, {raw}: {len(log)} transactions ({raw.stat().st_size} bus bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
