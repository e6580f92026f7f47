"""libmodbus's unit tests through ``mbmon proxy``, as byte tables (no libmodbus in
CI): every request libmodbus's ``unit-test-client tcp`` sends and the answer its
``unit-test-server`` gives, recorded through the proxy, replayed between a raw
client and a scripted upstream. Both TCP modes pass every exchange byte for byte:
exception answers, answers whose byte count disagrees with the request, requests
libmodbus makes malformed on purpose (forwarded untouched: no guard is on), the
server that answers tid 0x27 with tid 0 (no made-up 0x0B follows), unit 0 and an
unknown unit. (The special timings -- an answer 500 ms late, one sent a byte every
5 ms -- are in test_proxy_answers.py.)
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.proxy.test_proxy_answers import read_adu, silence, through_proxy

#: (request ADU, answer ADU) in libmodbus's order (unit-test-client.c, unit-test-server.c)
SESSION = [
    ("00 01 00 00 00 06 FF 05 01 30 FF 00", "00 01 00 00 00 06 FF 05 01 30 FF 00"),
    ("00 02 00 00 00 06 FF 01 01 30 00 01", "00 02 00 00 00 04 FF 01 01 01"),
    (
        "00 03 00 00 00 0C FF 0F 01 30 00 25 05 CD 6B B2 0E 1B",
        "00 03 00 00 00 06 FF 0F 01 30 00 25",
    ),
    ("00 04 00 00 00 06 FF 01 01 30 00 25", "00 04 00 00 00 08 FF 01 05 CD 6B B2 0E 1B"),
    ("00 05 00 00 00 06 FF 02 01 C4 00 16", "00 05 00 00 00 06 FF 02 03 AC DB 35"),
    ("00 06 00 00 00 06 FF 06 01 60 12 34", "00 06 00 00 00 06 FF 06 01 60 12 34"),
    ("00 07 00 00 00 06 FF 03 01 60 00 01", "00 07 00 00 00 05 FF 03 02 12 34"),
    (
        "00 08 00 00 00 0D FF 10 01 60 00 03 06 02 2B 00 01 00 64",
        "00 08 00 00 00 06 FF 10 01 60 00 03",
    ),
    ("00 09 00 00 00 06 FF 03 01 60 00 03", "00 09 00 00 00 09 FF 03 06 02 2B 00 01 00 64"),
    (
        "00 0A 00 00 00 0F FF 17 01 60 00 03 01 61 00 02 04 00 00 00 00",
        "00 0A 00 00 00 09 FF 17 06 02 2B 00 00 00 00",
    ),
    ("00 0B 00 00 00 06 FF 04 01 08 00 01", "00 0B 00 00 00 05 FF 04 02 00 0A"),
    ("00 0C 00 00 00 06 FF 06 01 60 00 12", "00 0C 00 00 00 06 FF 06 01 60 00 12"),
    ("00 0D 00 00 00 08 FF 16 01 60 00 F2 00 25", "00 0D 00 00 00 08 FF 16 01 60 00 F2 00 25"),
    ("00 0E 00 00 00 06 FF 03 01 60 00 01", "00 0E 00 00 00 05 FF 03 02 00 17"),
    ("00 0F 00 00 00 06 FF 01 00 00 00 01", "00 0F 00 00 00 03 FF 81 02"),
    ("00 10 00 00 00 06 FF 01 01 30 00 26", "00 10 00 00 00 03 FF 81 02"),
    ("00 11 00 00 00 06 FF 02 00 00 00 01", "00 11 00 00 00 03 FF 82 02"),
    ("00 12 00 00 00 06 FF 02 01 C4 00 17", "00 12 00 00 00 03 FF 82 02"),
    ("00 13 00 00 00 06 FF 03 00 00 00 01", "00 13 00 00 00 03 FF 83 02"),
    ("00 14 00 00 00 06 FF 03 01 60 00 21", "00 14 00 00 00 03 FF 83 02"),
    ("00 15 00 00 00 06 FF 04 00 00 00 01", "00 15 00 00 00 03 FF 84 02"),
    ("00 16 00 00 00 06 FF 04 01 08 00 02", "00 16 00 00 00 03 FF 84 02"),
    ("00 17 00 00 00 06 FF 05 00 00 FF 00", "00 17 00 00 00 03 FF 85 02"),
    ("00 18 00 00 00 06 FF 05 01 55 FF 00", "00 18 00 00 00 03 FF 85 02"),
    ("00 19 00 00 00 08 FF 0F 00 00 00 01 01 00", "00 19 00 00 00 03 FF 8F 02"),
    ("00 1A 00 00 00 0C FF 0F 01 55 00 25 05 AC DB B5 0E 1B", "00 1A 00 00 00 03 FF 8F 02"),
    ("00 1B 00 00 00 06 FF 06 00 00 20 00", "00 1B 00 00 00 03 FF 86 02"),
    ("00 1C 00 00 00 06 FF 06 01 80 20 00", "00 1C 00 00 00 03 FF 86 02"),
    ("00 1D 00 00 00 09 FF 10 00 00 00 01 02 20 00", "00 1D 00 00 00 03 FF 90 02"),
    ("00 1E 00 00 00 0D FF 10 01 80 00 03 06 20 00 47 F1 00 00", "00 1E 00 00 00 03 FF 90 02"),
    ("00 1F 00 00 00 08 FF 16 00 00 00 F2 00 25", "00 1F 00 00 00 03 FF 96 02"),
    ("00 20 00 00 00 08 FF 16 01 80 00 F2 00 25", "00 20 00 00 00 03 FF 96 02"),
    ("00 21 00 00 00 0D FF 17 00 00 00 01 00 00 00 01 02 20 00", "00 21 00 00 00 03 FF 97 02"),
    (
        "00 22 00 00 00 11 FF 17 01 80 00 03 01 80 00 03 06 20 00 47 F1 00 00",
        "00 22 00 00 00 03 FF 97 02",
    ),
    ("00 23 00 00 00 06 FF 05 01 32 FF 00", "00 23 00 00 00 03 FF 85 03"),
    ("00 24 00 00 00 06 FF 06 01 70 00 42", "00 24 00 00 00 03 FF 86 03"),
    ("00 25 00 00 00 06 12 03 01 60 00 03", "00 25 00 00 00 09 12 03 06 00 17 00 00 00 00"),
    ("00 26 00 00 00 06 00 03 01 60 00 03", "00 26 00 00 00 09 00 03 06 00 17 00 00 00 00"),
    (
        "00 27 00 00 00 06 FF 03 01 71 00 01",
        "00 00 00 00 00 05 FF 03 02 00 00",
    ),  # answered with tid 0
    ("00 28 00 00 00 02 FF 11", "00 28 00 00 00 0E FF 11 0B B4 FF 4C 4D 42 33 2E 31 2E 31 32"),
    ("00 29 00 00 00 02 FF 11", "00 29 00 00 00 0E FF 11 0B B4 FF 4C 4D 42 33 2E 31 2E 31 32"),
    ("00 2A 00 00 00 06 FF 03 01 60 00 03", "00 2A 00 00 00 09 FF 03 06 00 17 00 00 00 00"),
    ("00 2B 00 00 00 06 FF 03 01 72 00 01", "00 2B 00 00 00 05 FF 03 02 00 00"),
    ("00 2C 00 00 00 06 FF 03 01 72 00 01", "00 2C 00 00 00 05 FF 03 02 00 00"),
    ("00 2D 00 00 00 06 FF 03 01 72 00 01", "00 2D 00 00 00 05 FF 03 02 00 00"),
    ("00 2E 00 00 00 06 FF 03 01 73 00 01", "00 2E 00 00 00 05 FF 03 02 00 00"),
    ("00 2F 00 00 00 06 FF 03 01 73 00 01", "00 2F 00 00 00 05 FF 03 02 00 00"),
    ("00 30 00 00 00 06 FF 03 01 60 00 02", "00 30 00 00 00 05 FF 03 02 00 17"),
    ("00 31 00 00 00 06 FF 03 01 70 00 03", "00 31 00 00 00 03 FF 83 06"),
    (
        "00 00 00 00 00 06 FF 03 01 60 00 05",
        "00 00 00 00 00 0D FF 03 0A 00 17 00 00 00 00 00 00 00 00",
    ),
    ("00 00 00 00 00 06 FF 01 01 60 00 00", "00 00 00 00 00 03 FF 81 03"),
    ("00 00 00 00 00 06 FF 01 01 60 07 D1", "00 00 00 00 00 03 FF 81 03"),
    ("00 00 00 00 00 06 FF 02 01 60 00 00", "00 00 00 00 00 03 FF 82 03"),
    ("00 00 00 00 00 06 FF 02 01 60 07 D1", "00 00 00 00 00 03 FF 82 03"),
    ("00 00 00 00 00 06 FF 03 01 60 00 00", "00 00 00 00 00 03 FF 83 03"),
    ("00 00 00 00 00 06 FF 03 01 60 00 7E", "00 00 00 00 00 03 FF 83 03"),
    ("00 00 00 00 00 06 FF 04 01 60 00 00", "00 00 00 00 00 03 FF 84 03"),
    ("00 00 00 00 00 06 FF 04 01 60 00 7E", "00 00 00 00 00 03 FF 84 03"),
    ("00 00 00 00 00 0D FF 17 01 60 00 00 00 00 00 01 02 12 34", "00 00 00 00 00 03 FF 97 03"),
    ("00 00 00 00 00 0D FF 17 01 60 00 7E 00 00 00 01 02 12 34", "00 00 00 00 00 03 FF 97 03"),
    ("00 00 00 00 00 0D FF 10 01 60 00 00 00 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 90 03"),
    ("00 00 00 00 00 0D FF 10 01 60 00 7C 06 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 90 03"),
    ("00 00 00 00 00 0D FF 0F 01 60 00 00 00 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 8F 03"),
    ("00 00 00 00 00 0D FF 0F 01 60 07 B1 06 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 8F 03"),
    ("00 00 00 00 00 0D FF 10 01 60 00 00 00 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 90 03"),
    ("00 00 00 00 00 0D FF 10 01 60 00 7B 06 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 90 03"),
    ("00 00 00 00 00 0D FF 0F 01 60 00 00 00 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 8F 03"),
    ("00 00 00 00 00 0D FF 0F 01 60 07 B0 06 02 2B 00 01 00 64", "00 00 00 00 00 03 FF 8F 03"),
    ("00 00 00 00 00 06 FF 42 00 00 00 00", "00 00 00 00 00 03 FF C2 01"),
]


def canned_upstream(errors: list[str]):
    """Answers the session's requests in order: the recorded answer with the id the
    request came with (the recorded one when the server answered another id)."""
    expected = iter(SESSION)

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                got = await read_adu(reader)
                want_req, want_ans = (bytes.fromhex(x) for x in next(expected))
                if got[2:] != want_req[2:]:
                    errors.append(f"upstream got {got.hex(' ')}, expected {want_req.hex(' ')}")
                if want_ans[:2] == want_req[:2]:
                    want_ans = got[:2] + want_ans[2:]
                writer.write(want_ans)
        except (asyncio.IncompleteReadError, ConnectionError, StopIteration):
            pass
        finally:
            writer.close()

    return handle


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_libmodbus_session_passes_byte_for_byte(tmp_path: Path, shared: bool) -> None:
    errors: list[str] = []
    extra = ["--share-upstream"] if shared else []

    async def main() -> str:
        async with through_proxy(
            canned_upstream(errors), tmp_path, "--timeout", "0.3", *extra
        ) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            for request, answer in SESSION:
                writer.write(bytes.fromhex(request))
                got = await asyncio.wait_for(read_adu(reader), 5)
                if got != bytes.fromhex(answer):
                    errors.append(f"{request}: got {got.hex(' ').upper()}, expected {answer}")
                if request.startswith("00 27 "):  # a made-up 0x0B would come now
                    extra_bytes = await silence(reader, 0.6)
                    if extra_bytes:
                        errors.append(f"after tid 0x27: {extra_bytes.hex(' ')}")
            assert await silence(reader, 0.4) == b""
            writer.close()
        return p.summary

    err = asyncio.run(main())
    assert errors == []
    assert f"requests {len(SESSION)}, responses {len(SESSION)}" in err
    assert "exceptions made by the proxy 0" in err
