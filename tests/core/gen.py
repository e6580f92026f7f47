"""Generated captures for the differential suites: one TCP conversation per file,
written segment by segment with chosen cuts, retransmissions, holes and noise."""

from __future__ import annotations

import itertools
from pathlib import Path

from mbmon.io.pcap import PcapngWriter, PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)

T0 = 1_700_000_000.25


def every_function_pair() -> list[tuple[bytes, bytes]]:
    """A request and its answer (PDUs) for the common and the rarer function codes."""
    pairs = [
        (encode_read_request(1, 10, 11), encode_read_response(1, [1, 0, 1] * 3 + [1, 1], 11)),
        (encode_read_request(2, 0, 70), encode_read_response(2, [1] * 70, 70)),
        (encode_read_request(3, 100, 3), encode_read_response(3, [1, 65535, 300])),
        (encode_read_request(4, 0, 20), encode_read_response(4, list(range(20)))),
        (encode_write_single(5, 7, 1), encode_write_single(5, 7, 1)),
        (encode_write_single(5, 8, 0), encode_write_single(5, 8, 0)),
        (encode_write_single(6, 200, 1234), encode_write_single(6, 200, 1234)),
        (
            encode_write_multiple_request(15, 3, [1, 0, 1, 1, 0, 0, 1, 0, 1]),
            encode_write_multiple_response(15, 3, 9),
        ),
        (
            encode_write_multiple_request(16, 200, list(range(18))),
            encode_write_multiple_response(16, 200, 18),
        ),
        (encode_read_request(3, 5, 2), encode_exception(3, 2)),
        (encode_read_request(4, 5, 2), encode_exception(4, 0x0B)),
        (b"\x07", b"\x07\x05"),  # read exception status
        (b"\x08\x00\x00\x12\x34", b"\x08\x00\x00\x12\x34"),  # diagnostics echo
        (b"\x0b", b"\x0b\x00\x00\x00\x05"),  # comm event counter
        (b"\x11", b"\x11\x05\x01\xff\x02\x03"),  # report server id
        (b"\x16\x00\x04\x00\xf2\x00\x25", b"\x16\x00\x04\x00\xf2\x00\x25"),  # mask write
        (
            b"\x17\x00\x03\x00\x02\x00\x0e\x00\x01\x02\x00\xff",
            b"\x17\x04\x00\x0a\x00\x0b",
        ),  # read/write multiple
        (b"\x18\x04\xde", b"\x18\x00\x06\x00\x02\x01\xb8\x12\x84"),  # FIFO
        (b"\x2b\x0e\x01\x00", b"\x2b\x0e\x01\x01\x00\x00\x01\x00\x03ABC"),  # device id
        (b"\x41\x01\x02", b"\x41\x03"),  # user-defined
        (encode_read_request(3, 0, 1), encode_read_response(3, [1, 2])),  # count disagrees
        (b"\x03\x00\x00\x00\x00", b"\x83\x03"),  # count 0: malformed request
        (b"\x06\x00\x01", b"\x86\x03\x00"),  # truncated request, exception with a trailing byte
        (b"\x01\x00\x00\x00\x08", b"\x01\x02\xff\xff"),  # byte count breaks the request
        (b"\x90\x00", b"\x90\x00"),  # the exception bit in a request
        (b"\x08\x00\x04\x00\x00", b"\x08\x00\x04\x00\x00"),  # listen only: never pending
    ]
    return pairs


def adus(pairs: list[tuple[bytes, bytes]], unit: int = 1) -> list[tuple[bool, bytes]]:
    """(from client, ADU) for each request and answer, transaction ids from 1."""
    out = []
    for tid, (req, resp) in enumerate(pairs, 1):
        out.append((True, encode_adu(tid, unit, req)))
        out.append((False, encode_adu(tid, unit, resp)))
    return out


def polling_capture(path: Path, pairs: int) -> Path:
    """A capture of ``pairs`` reads of ten holding registers and their answers, values
    changing every poll (one ADU per segment): logs of several ~1 MiB blocks."""
    segments: list[tuple[bool, bytes]] = []
    for i in range(pairs):
        tid = i % 65536
        values = [(i * 7 + k * 13) & 0xFFFF for k in range(10)]
        segments.append((True, encode_adu(tid, 1, encode_read_request(3, 100, 10))))
        segments.append((False, encode_adu(tid, 1, encode_read_response(3, values))))
    return write_conversation(path, segments)


def write_conversation(
    path: Path,
    segments: list[tuple[bool, bytes]],
    *,
    handshake: bool = True,
    close: str | None = "fin",
    step: float = 0.001,
    linktype: int = 1,
    pcapng: bool = False,
    times: list[float] | None = None,
    vlans: tuple[tuple[int, int], ...] = (),
) -> Path:
    """A capture of one connection: optional handshake, ``segments`` (from client,
    payload) each one segment (PSH|ACK), then a FIN close, a RST or nothing."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502", linktype=linktype, vlans=vlans)
    frames: list[bytes] = []
    if handshake:
        frames += conv.open()
    else:
        conv.client_next, conv.server_next = 1001, 5001
    frames += [conv.send(c, data) for c, data in segments]
    if close == "fin":
        frames += conv.close(True)
    elif close == "rst":
        frames.append(conv.reset(False))
    stamps = times if times is not None else [T0 + i * step for i in range(len(frames))]
    if pcapng:
        with PcapngWriter(path) as w:
            w.add_interface(linktype)
            for ts, frame in zip(stamps, frames, strict=False):
                w.write(ts, frame)
    else:
        with PcapWriter(path, linktype) as w:
            for ts, frame in zip(stamps, frames, strict=False):
                w.write(ts, frame)
    return path


def write_frames(path: Path, frames: list[tuple[float, bytes]], linktype: int = 1) -> Path:
    with PcapWriter(path, linktype) as w:
        for ts, frame in frames:
            w.write(ts, frame)
    return path


# ---------------------------------------------------------------- scenarios shared by suites


def split_at_every_byte(folder: Path) -> list[Path]:
    """Two pipelined requests cut at every byte (one file per cut, the answer to the
    first between the two halves): the scenario the file and live suites both run."""
    req = encode_adu(7, 1, encode_read_request(3, 10, 4))
    resp = encode_adu(7, 1, encode_read_response(3, [1, 2, 3, 4]))
    nxt = encode_adu(8, 1, encode_read_request(4, 0, 1))
    both = req + nxt
    return [
        write_conversation(
            folder / f"split{cut}.pcap", [(True, both[:cut]), (False, resp), (True, both[cut:])]
        )
        for cut in range(1, len(both))
    ]


def retransmission_and_overlap(folder: Path) -> Path:
    """A request retransmitted whole, then a segment overlapping its last 3 bytes with
    the next request; both answered, then FIN from the server."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    req2 = encode_adu(2, 1, encode_read_request(3, 2, 2))
    seq = conv.client_next
    frames.append(conv.send(True, req))
    frames.append(conv.segment(True, 0x18, req, seq=seq, advance=False))  # retransmitted
    frames.append(conv.segment(True, 0x18, req[-3:] + req2, seq=seq + len(req) - 3))
    conv.client_next = (seq + len(req) + len(req2)) & 0xFFFFFFFF
    frames.append(conv.send(False, encode_adu(1, 1, encode_read_response(3, [1, 2]))))
    frames.append(conv.send(False, encode_adu(2, 1, encode_read_response(3, [3, 4]))))
    frames += conv.close(False)
    return write_frames(folder / "rtx.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])


def noisy_stream(seed: int) -> list[tuple[bool, bytes]]:
    """(from client, bytes) of a conversation of every function pair with noise between
    and inside ADUs (garbage, bad protocol ids and lengths, header-like zeros, a
    capture begun mid-ADU) and ADUs of MBAP length 255, chosen by ``seed``."""
    import random

    rng = random.Random(seed)
    out: list[tuple[bool, bytes]] = []
    junk = [
        b"\x01\x02\x03garbage!",
        b"\x00\x00\x00\x00\x00\x00\x00",
        b"\x12\x34\x00\x01\x00\x06\x01\x03",  # protocol id 1
        b"\x00\x05\x00\x00\x01\x00\x01",  # length 256
        b"\x00\x00",
        b"\xff",
    ]
    for client, adu in adus(every_function_pair()):
        roll = rng.random()
        if roll < 0.15:
            adu = rng.choice(junk) + adu
        elif roll < 0.2:
            adu = adu[rng.randrange(1, len(adu)) :]  # its start lost
        elif roll < 0.25:
            adu = adu + bytes(rng.randrange(256) for _ in range(rng.randrange(1, 12)))
        elif roll < 0.3:
            tid = rng.randrange(1 << 16)
            adu = bytes((tid >> 8, tid & 255, 0, 0, 0, 255, 1, 0x5A)) + bytes(253) + adu
        out.append((client, adu))
    return out


def reordered_conversation(
    path: Path,
    seed: int,
    *,
    close: str | None = "fin",
    handshake: bool = True,
    replace: bool = False,
) -> Path:
    """A capture of one connection (every function pair, ADUs cut in pieces) whose
    segments, the close among them, were reordered, lost and duplicated as ``seed``
    picks: out-of-order segments, holes that ACKs pass or the end gives up, FINs
    ahead of data, retransmissions; with ``replace`` a new connection on the same
    addresses opens while this one is open."""
    import random

    from mbmon.io.pcap.packets import ACK, PSH

    rng = random.Random(seed)
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    head: list[bytes] = conv.open() if handshake else []
    if not handshake:
        conv.client_next, conv.server_next = 1001, 5001
    body: list[bytes] = []
    for client, adu in adus(every_function_pair()):
        cuts = sorted(rng.sample(range(1, len(adu)), k=min(rng.randrange(3), len(adu) - 1)))
        for a, b in itertools.pairwise([0, *cuts, len(adu)]):
            body.append(conv.send(client, adu[a:b]))
    if close == "fin":
        body += conv.close(rng.random() < 0.5)
    elif close == "rst":
        body.append(conv.reset(rng.random() < 0.5))
    frames: list[bytes] = []
    i = 0
    while i < len(body):
        roll = rng.random()
        if roll < 0.12 and i + 2 < len(body):
            j = i + rng.randrange(1, 3)
            frames += [body[j], *body[i:j]]  # one segment ahead of those before it
            i = j + 1
            continue
        if roll < 0.17:
            i += 1  # lost by the capture
            continue
        frames.append(body[i])
        if roll < 0.22:
            frames.append(body[i])  # retransmitted
        i += 1
    if replace:
        at = rng.randrange(len(frames) + 1)
        new = TcpConversation(
            "10.0.0.1:40000", "10.0.0.2:502", client_isn=rng.randrange(1 << 32), server_isn=7
        )
        more = new.open() + [
            new.segment(c, PSH | ACK, a) for c, a in adus(every_function_pair()[:4])
        ]
        if rng.random() < 0.5:
            more = more[1:]  # its SYN not captured: the SYN-ACK opens it
        frames[at:at] = more
    stamps = [T0 + 0.002 * n for n in range(len(head) + len(frames))]
    return write_frames(path, list(zip(stamps, head + frames, strict=True)))


def perturbed_capture(src: Path, dst: Path, seed: int, *, rate: float = 0.05) -> Path:
    """A classic pcap ``src`` with its records reordered (one ahead of up to three
    before it), lost and duplicated at about ``rate`` each, as ``seed`` picks: a real
    capture's holes, out-of-order segments and retransmissions. Times stay each
    record's own (they go backwards where records moved)."""
    import random

    rng = random.Random(seed)
    data = src.read_bytes()
    big = data[:4] in (b"\xa1\xb2\xc3\xd4", b"\xa1\xb2\x3c\x4d")
    records, pos = [], 24
    while pos + 16 <= len(data):
        caplen = int.from_bytes(data[pos + 8 : pos + 12], "big" if big else "little")
        records.append(data[pos : pos + 16 + caplen])
        pos += 16 + caplen
    out: list[bytes] = []
    i = 0
    while i < len(records):
        roll = rng.random()
        if roll < rate and i + 2 < len(records):
            j = i + rng.randrange(1, min(4, len(records) - i))
            out += [records[j], *records[i:j]]
            i = j + 1
            continue
        if roll < 2 * rate:
            i += 1
            continue
        out.append(records[i])
        if roll < 3 * rate:
            out.append(records[i])
        i += 1
    dst.write_bytes(data[:24] + b"".join(out))
    return dst


def udp_exchange(
    path: Path,
    datagrams: list[tuple[bool, bytes]],
    *,
    client: str = "10.0.0.1:40000",
    server: str = "10.0.0.2:502",
    linktype: int = 1,
    step: float = 0.001,
) -> Path:
    """A capture of Modbus/UDP: each (from client, payload) one datagram."""
    from mbmon.io.pcap.packets import parse_endpoint, udp_frame

    (cip, cport), (sip, sport) = parse_endpoint(client), parse_endpoint(server)
    frames = []
    for n, (from_client, payload) in enumerate(datagrams):
        if from_client:
            frame = udp_frame(linktype, cip, sip, cport, sport, payload)
        else:
            frame = udp_frame(linktype, sip, cip, sport, cport, payload)
        frames.append((T0 + n * step, frame))
    return write_frames(path, frames, linktype)


def ipv6_segment(
    conv: TcpConversation,
    from_client: bool,
    flags: int,
    payload: bytes = b"",
    *,
    extensions: tuple[tuple[int, bytes], ...] = (),
) -> bytes:
    """One segment of an IPv6 ``conv`` (Ethernet) with IPv6 extension headers; the
    conversation's numbers move on as :meth:`TcpConversation.segment` moves them."""
    from mbmon.io.pcap.packets import ethernet_frame, ipv6_packet, tcp_header

    if from_client:
        src, sport, dst, dport = conv.client_ip, conv.client_port, conv.server_ip, conv.server_port
        seq, ack = conv.client_next, conv.server_next
    else:
        src, sport, dst, dport = conv.server_ip, conv.server_port, conv.client_ip, conv.client_port
        seq, ack = conv.server_next, conv.client_next
    segment = tcp_header(src, dst, sport, dport, seq, ack, flags, payload)
    end = (seq + len(payload) + (1 if flags & 0x03 else 0)) & 0xFFFFFFFF
    if from_client:
        conv.client_next = end
    else:
        conv.server_next = end
    return ethernet_frame(ipv6_packet(src, dst, 6, segment, extensions=extensions), 0x86DD)
