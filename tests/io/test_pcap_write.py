"""The pcap writer: byte layouts checked against published examples and tshark."""

from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import pytest

from mbmon.io import pcap
from mbmon.io.pcap import (
    LINKTYPE_ETHERNET,
    LINKTYPE_USER0,
    PcapngWriter,
    PcapWriter,
    TcpConversation,
    ipv4_packet,
    parse_endpoint,
    udp_frame,
)

TSHARK = shutil.which("tshark")


def test_ipv4_header_checksum_matches_the_textbook_example() -> None:
    # The classic worked example (Wikipedia "Internet checksum"): 45 00 00 73 00 00
    # 40 00 40 11 [b8 61] c0 a8 00 01 c0 a8 00 c7, 0x73 - 20 = 95 payload bytes.
    packet = ipv4_packet("192.168.0.1", "192.168.0.199", 17, bytes(95), ttl=64)
    assert packet[:20] == bytes.fromhex(
        "450000730000400040 11b861c0a80001c0a800c7".replace(" ", "")
    )


def test_parse_endpoint_handles_ipv4_and_bracketed_ipv6() -> None:
    assert parse_endpoint("10.0.0.1:502") == ("10.0.0.1", 502)
    assert parse_endpoint("[fe80::1]:1502") == ("fe80::1", 1502)


def test_pcap_file_header_and_record_layout(tmp_path: Path) -> None:
    path = tmp_path / "x.pcap"
    with PcapWriter(path, LINKTYPE_USER0, nanosecond=True, big_endian=True) as writer:
        writer.write(1.5, b"\x01\x03")
    data = path.read_bytes()
    assert data[:24] == struct.pack(">IHHiIII", 0xA1B23C4D, 2, 4, 0, 0, 262144, 147)
    assert data[24:] == struct.pack(">IIII", 1, 500_000_000, 2, 2) + b"\x01\x03"


def test_pcapng_blocks_are_well_formed(tmp_path: Path) -> None:
    path = tmp_path / "x.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(LINKTYPE_ETHERNET, tsresol=9)
        writer.write(2.0, b"abc")
    data = path.read_bytes()
    pos = 0
    types = []
    while pos < len(data):
        btype, blen = struct.unpack_from("<II", data, pos)
        assert blen % 4 == 0
        assert struct.unpack_from("<I", data, pos + blen - 4)[0] == blen
        types.append(btype)
        pos += blen
    assert types == [0x0A0D0D0A, 1, 6]
    # EPB timestamp in nanoseconds: 2.0 s = 2e9 units
    epb = data[-(12 + 20 + 4) :]  # header, iface/ts/lengths, 3 data bytes + pad
    assert struct.unpack_from("<III", epb, 8) == (0, 0, 2_000_000_000)


def test_pcapng_packet_and_section_comments_are_opt_comment_options(tmp_path: Path) -> None:
    """EPB: data padded, then one ``opt_comment`` (code 1) per comment and the end of
    options; the section comment is put in a finished file in either byte order."""
    for big, e in ((False, "<"), (True, ">")):
        path = tmp_path / f"c{int(big)}.pcapng"
        with PcapngWriter(path, big_endian=big) as writer:
            writer.add_interface(LINKTYPE_ETHERNET, tsresol=9)
            writer.write(2.0, b"abc", comments=["lost 3", "port"])
            writer.write(3.0, b"de")  # no comment: no options at all
        plain = path.read_bytes()
        PcapngWriter.comment_first_section(path, ["two rewrites", "é"])
        data = path.read_bytes()
        shb_len = struct.unpack_from(e + "I", data, 4)[0]
        old_len = struct.unpack_from(e + "I", plain, 4)[0]
        assert data[shb_len:] == plain[old_len:]  # every other block as it was
        assert struct.unpack_from(e + "I", data, shb_len - 4)[0] == shb_len
        options = data[8 + 16 : shb_len - 4]
        assert options == (
            struct.pack(e + "HH", 1, 12) + b"two rewrites"
            + struct.pack(e + "HH", 1, 2) + "é".encode() + b"\0\0"
            + struct.pack(e + "HH", 4, 5) + b"mbmon\0\0\0"
            + struct.pack(e + "HH", 0, 0)
        )  # fmt: skip
        pos = shb_len
        pos += struct.unpack_from(e + "I", data, pos + 4)[0]  # the IDB
        epb_len = struct.unpack_from(e + "I", data, pos + 4)[0]
        epb = data[pos : pos + epb_len]
        assert epb[28:] == (
            b"abc\0"
            + struct.pack(e + "HH", 1, 6) + b"lost 3\0\0"
            + struct.pack(e + "HH", 1, 4) + b"port"
            + struct.pack(e + "HH", 0, 0)
            + struct.pack(e + "I", epb_len)
        )  # fmt: skip
        second = data[pos + epb_len :]
        assert len(second) == 12 + 20 + 4 and second[28:32] == b"de\0\0"
        assert not list(tmp_path.glob("*.tmp"))


def _tshark_fields(path: Path, *fields: str) -> list[list[str]]:
    assert TSHARK is not None
    args = [TSHARK, "-r", str(path), "-o", "tcp.relative_sequence_numbers:FALSE"]
    args += ["-o", "tcp.check_checksum:TRUE", "-o", "udp.check_checksum:TRUE", "-T", "fields"]
    for field in fields:
        args += ["-e", field]
    result = subprocess.run(args, capture_output=True, text=True, check=True)
    return [line.split("\t") for line in result.stdout.splitlines()]


@pytest.mark.skipif(TSHARK is None, reason="tshark not installed")
@pytest.mark.parametrize("client", ["10.1.2.3:40001", "[2001:db8::5]:40001"])
def test_tshark_sees_a_clean_conversation(tmp_path: Path, client: str) -> None:
    server = "10.1.2.4:502" if "." in client else "[2001:db8::6]:502"
    conv = TcpConversation(client, server, client_isn=0xFFFFFFF0, server_isn=77)
    path = tmp_path / "conv.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(LINKTYPE_ETHERNET)
        frames = [
            *conv.open(),
            conv.send(True, bytes.fromhex("000100000006010300000002")),
            conv.send(False, bytes.fromhex("00010000000701030400010002")),
            *conv.close(True),
        ]
        for i, frame in enumerate(frames):
            writer.write(100.0 + i, frame)
    rows = _tshark_fields(
        path, "tcp.seq", "tcp.ack", "tcp.len", "tcp.checksum.status", "_ws.expert.message"
    )
    assert len(rows) == 8
    assert {row[3] for row in rows} == {"1"}  # every TCP checksum verified good
    # No analysis warnings (retransmission, lost segment, ...) anywhere.
    assert [row[4] for row in rows] == [
        "Connection establish request (SYN): server port 502",
        "Connection establish acknowledge (SYN+ACK): server port 502",
        "",
        "",
        "",
        "Connection finish (FIN),This frame initiates the connection closing",
        "Connection finish (FIN),This frame undergoes the connection closing",
        "",
    ]
    # Sequence numbers wrap across 2^32 in the client direction.
    assert rows[3][:3] == [str(0xFFFFFFF1), "78", "12"]
    assert rows[5][0] == str((0xFFFFFFF1 + 12) & 0xFFFFFFFF)


@pytest.mark.skipif(TSHARK is None, reason="tshark not installed")
@pytest.mark.parametrize(
    "linktype",
    [
        pcap.LINKTYPE_NULL,
        pcap.LINKTYPE_ETHERNET,
        pcap.LINKTYPE_RAW,
        pcap.LINKTYPE_LOOP,
        pcap.LINKTYPE_LINUX_SLL,
        pcap.LINKTYPE_IPV4,
        pcap.LINKTYPE_LINUX_SLL2,
    ],
)
def test_tshark_decodes_every_link_layer(tmp_path: Path, linktype: int) -> None:
    path = tmp_path / f"link{linktype}.pcap"
    with PcapWriter(path, linktype) as writer:
        writer.write(1.0, udp_frame(linktype, "10.0.0.1", "10.0.0.2", 5000, 502, b"\x00\x01"))
    assert _tshark_fields(path, "ip.src", "udp.dstport", "udp.checksum.status") == [
        ["10.0.0.1", "502", "1"]
    ]
