"""Bus health and the two-tap merge, driven through a real Hub and Pipeline (no ports).

Reads are given as chunks with the timestamps an adapter would give them: a
prompt adapter (one read per frame, gaps as on the wire), an FTDI adapter with
its 16 ms latency timer (reads in bursts), and a listener at the wrong baud
rate (bytes that frame as nothing).
"""

from __future__ import annotations

import random

from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Event, EventKind, Transport
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.rtu import encode_rtu
from mbmon.sources.serial import BusHealth, SerialSettings, TimeMerge

SETTINGS = SerialSettings(115200)
REQ = encode_rtu(1, bytes.fromhex("0300000002"))
RESP = encode_rtu(1, bytes.fromhex("030400010002"))


def _run(reads: list[tuple[float, bytes]], settings: SerialSettings = SETTINGS):
    hub = Hub(Pipeline(None, PipelineConfig(baudrate=settings.baudrate)))
    stream = hub.new_stream(Transport.RTU, "bus", "bus")
    emitted: list[Event] = []
    health = BusHealth(stream, settings, emitted.append, stats_every=1.0)
    hub.add_listener(health)
    for ts, data in reads:
        hub.feed(Chunk(ts, stream, Direction.BUS, data))
        hub.tick(ts)
    hub.tick(reads[-1][0] + 2.0)
    hub.tick(reads[-1][0] + 4.0)
    hub.finish()
    return health, emitted


def test_prompt_adapter_gaps_histogram_and_t35_violations():
    char = SETTINGS.char_time()
    reads = []
    t = 100.0
    for i in range(30):
        t += len(REQ) * char
        reads.append((t, REQ))
        t += 0.004 + len(RESP) * char  # the slave answers after 4 ms
        reads.append((t, RESP))
        # the next request: after 20 ms, but every 10th back to back (no t3.5 silence)
        t += 0.0005 if i % 10 == 9 else 0.020
    health, emitted = _run(reads)
    assert health.frames == 60
    assert health.noise_bytes == 0 and health.crc_errors == 0
    labels = dict(zip(health.gap_labels(), health.gaps, strict=True))
    assert labels["lt_5ms"] == 30  # the 4 ms answers
    assert labels["lt_50ms"] == 27  # the 20 ms pauses (29 between exchanges, 2 short)
    assert health.t35_violations == 2 and labels["lt_t35"] == 2
    assert not health.bursty() and not health.warned_bursts
    stats = [e for e in emitted if e.kind is EventKind.STATS]
    assert stats and stats[-1].info["frames"] == 60 and stats[-1].info["t35_violations"] == 2
    assert not [e for e in emitted if e.kind is EventKind.NOTICE]


def test_ftdi_bursts_make_timing_useless_and_say_so():
    traffic = (REQ + RESP) * 40
    reads = []
    t = 200.0
    for pos in range(0, len(traffic), 29):  # what 16 ms of a busy 115200 line holds, roughly
        t += 0.016
        reads.append((t, traffic[pos : pos + 29]))
    health, emitted = _run(reads)
    assert health.frames == 80  # framing by length and CRC does not care
    assert health.bursty()
    notices = [e.info["message"] for e in emitted if e.kind is EventKind.NOTICE]
    assert len(notices) == 1
    assert "bursts about 16 ms apart" in notices[0] and "latency_timer" in notices[0]
    assert any("NOT meaningful" in line for line in health.summary())


def test_wrong_baud_rate_noise_warning():
    rng = random.Random(3)
    # what a 9600-baud bus looks like to a listener at 115200: bytes that frame as nothing
    reads = [(300.0 + i * 0.01, bytes(rng.randrange(256) for _ in range(16))) for i in range(40)]
    health, emitted = _run(reads)
    assert health.noise_bytes * 2 > health.bytes
    notices = [e.info["message"] for e in emitted if e.kind is EventKind.NOTICE]
    assert any("wrong baud rate" in n and "115200 8N1" in n for n in notices)


def test_time_merge_orders_reads_of_two_taps():
    clock = [0.0]
    merge = TimeMerge(0.05, clock=lambda: clock[0])
    hub = Hub(Pipeline(None, PipelineConfig(baudrate=115200)), clock=lambda: clock[0])
    hub.add_ticker(merge)
    stream = hub.new_stream(Transport.RTU, "A+B", "A+B")
    got = []

    class Collect:
        def on_records(self, records):
            got.extend(records)

    hub.add_listener(Collect())
    # the slave tap delivers its response read before the master tap's request read
    clock[0] = 10.010
    for item in merge.add(Chunk(10.006, stream, Direction.BUS, RESP)):
        hub.feed(item)
    for item in merge.add(Chunk(10.002, stream, Direction.BUS, REQ)):
        hub.feed(item)
    assert not got and merge.next_deadline() == 10.002 + 0.05
    hub.tick(10.060)
    kinds = [r.kind.value for r in got]
    assert kinds == ["request", "response"]
    assert got[1].latency is not None and abs(got[1].latency - 0.004) < 1e-9


def _screen(health: BusHealth) -> str:
    """The monitor's header with the bus figures ``sniff --serial`` hands it."""
    from mbmon.format import View
    from mbmon.monitor.feed import MonitorFeed

    monitor = MonitorFeed(View())
    monitor.set_figures(health.screen_figures())
    return monitor.header_text()


def test_live_screen_shows_the_bus_health_figures():
    char = SETTINGS.char_time()
    reads = []
    t = 100.0
    for i in range(30):
        t += len(REQ) * char
        reads.append((t, REQ))
        t += 0.004 + len(RESP) * char
        reads.append((t, RESP))
        t += 0.0005 if i % 10 == 9 else 0.020
    health, _ = _run(reads)
    text = _screen(health)
    assert "CRC failures 0" in text and "t3.5 violations 2" in text
    assert "gaps <t3.5:2 <5ms:30 <50ms:27" in text
    assert "reads every" in text and "warnings" not in text


def test_live_screen_keeps_the_burst_and_wrong_baud_warnings_in_its_header():
    traffic = (REQ + RESP) * 40
    reads = []
    t = 200.0
    for pos in range(0, len(traffic), 29):
        t += 0.016
        reads.append((t, traffic[pos : pos + 29]))
    bursty, _ = _run(reads)
    text = _screen(bursty)
    assert "reads every 16.0 ms" in text
    assert "warnings adapter bursts: timing not meaningful" in text
    assert "wrong baud" not in text

    rng = random.Random(3)
    noise = [(300.0 + i * 0.01, bytes(rng.randrange(256) for _ in range(16))) for i in range(40)]
    wrong, _ = _run(noise)
    assert "mostly noise: wrong baud rate or parity?" in _screen(wrong)
