"""The annotator's and the HRSS session's caches change no output.

``read --profile hrss`` remembers per (profile, table, address, count) what a
read shows and per (address, count) where the session's registers sit in an
FC 04 answer. These tests run the same traffic with every cache defeated
(nothing remembered, every layout built again) and with the caches warm, and
compare every output line and JSON record; and check that the session's state
values, read through its per-read plan, are what ``Field.raw``/``Field.value``
say for any words.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mbmon.semantics.annotate as annotate_mod
import mbmon.semantics.notes as notes_mod
from mbmon.format import View, record_line, record_to_json
from mbmon.model import Direction, Frame, Stream, Transaction, Transport, TxStatus
from mbmon.pipeline import Pipeline
from mbmon.protocol.pdu import decode_pdu, encode_read_request, encode_read_response
from mbmon.semantics.annotate import annotator_for
from mbmon.semantics.hrss import HrssSession, load_spec
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[2]
CAPTURES = REPO / "captures"
REAL = REPO.parent / "shared" / "captures" / "real"


def _bench_builder() -> Any:
    spec = importlib.util.spec_from_file_location("hrss_bench", REPO / "bench" / "hrss_session.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("hrss_bench", module)
    spec.loader.exec_module(module)
    return module.build_capture


@pytest.fixture(scope="module")
def cell_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generated HRSS cell session (commands, Get returns, changing state) of 6,000 ADUs."""
    path = tmp_path_factory.mktemp("hrss") / "cell.pcap"
    _bench_builder()(6000, path, seed=5)
    return path


def _lines(path: Path, specs: list[str]) -> Iterator[tuple[str, str]]:
    view = View(robot="192.168.0.10")
    for record in Pipeline(annotator_for(specs)).run(read_capture(path)):
        yield record_line(record, view), repr(record_to_json(record, view))


def _captures() -> list[Path]:
    """The project's captures, and the public real ones up to 400 kB (keeps the test short)."""
    found = [CAPTURES / "hrss_ptp.pcap", CAPTURES / "hrss_rtu.pcap"]
    if REAL.is_dir():
        found += sorted(
            p
            for p in REAL.iterdir()
            if p.suffix in (".pcap", ".pcapng") and p.stat().st_size <= 400_000
        )
    return found


@pytest.mark.parametrize("specs", [["hrss"], ["xeg"], ["hrss", "unit:2=xeg"]])
def test_cached_output_is_the_uncached_output(
    cell_capture: Path, specs: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    paths = [cell_capture, *_captures()]
    warm = {p: list(_lines(p, specs)) for p in paths}
    if "hrss" in specs:  # the session took part: commands completed, Get returns decoded
        shown = [line for line, _ in warm[cell_capture]]
        assert any(">> [success after " in line for line in shown)
        assert any(">> [returned] " in line for line in shown)
    with monkeypatch.context() as m:
        for module in (annotate_mod, notes_mod):  # every memo of notes and reads off
            m.setattr(module, "remember", lambda memo, key, value: None)
        build = HrssSession._read_plan

        def fresh(self: HrssSession, address: int, count: int) -> Any:
            plan = build(self, address, count)
            self._plans.clear()
            return plan

        m.setattr(HrssSession, "_read_plan", fresh)
        for p in paths:
            assert list(_lines(p, specs)) == warm[p], p.name


STREAM = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
SPEC = load_spec()
LOW = min(f.regs[0] for _k, f in SPEC.state)
HIGH = max(f.regs[-1] for _k, f in SPEC.state)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 0xFFFF), min_size=HIGH - LOW + 1, max_size=HIGH - LOW + 1),
    st.integers(0, HIGH - LOW),
    st.integers(1, 125),
)
def test_state_through_plans_is_what_fields_say(words: list[int], skip: int, count: int) -> None:
    """Any words, any window of them: the state is Field.value(Field.raw()) of complete fields."""
    start = LOW + skip
    window = words[skip : skip + count]
    if not window:
        return
    session = HrssSession(STREAM, 1)
    req_pdu = encode_read_request(0x04, start, len(window))
    req = Frame(1.0, STREAM, Direction.C2S, 1, 1, decode_pdu(req_pdu, False), req_pdu)
    resp_pdu = encode_read_response(0x04, window)
    resp = Frame(1.1, STREAM, Direction.S2C, 1, 1, decode_pdu(resp_pdu, True, req.pdu), resp_pdu)
    session.feed(Transaction(1.1, TxStatus.ANSWERED, req, resp, 0.1))
    image = {start + i: w for i, w in enumerate(window)}
    expected = {}
    for key, f in SPEC.state:
        raw = f.raw(image.get)
        if raw is not None:
            expected[key] = float(f.value(raw))
    assert session.state == expected
