"""HRSS command layouts (Tables 16-43) and the session's lifecycle rules, byte by byte.

The helper :class:`Script` turns Modbus PDUs into the frames and pairing steps
the pipeline would produce (PENDING for the request, ANSWERED/EXCEPTION with
latency for the answer) and feeds them to a real :class:`HrssSession`; the
other HRSS test modules import it.
"""

from __future__ import annotations

from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import (
    Annotation,
    CommandUpdate,
    Direction,
    Frame,
    Phase,
    Stream,
    Transaction,
    Transport,
    TxStatus,
)
from mbmon.protocol.pdu import (
    decode_pdu,
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)
from mbmon.semantics.hrss import (
    HrssSession,
    decode_command,
    decode_returns,
    format_scaled,
    load_spec,
)
from mbmon.semantics.words import split_i32, u16

STREAM = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")


def words(*values: int) -> list[int]:
    """Signed table values (as the manual prints them) as unsigned register words."""
    return [u16(v) for v in values]


def i32(value: float) -> list[int]:
    """A scaled value (0.001 units) as (low, high) unsigned words, Appendix II."""
    lo, hi = split_i32(round(value * 1000))
    return [u16(lo), u16(hi)]


def wr(address: int, values: Sequence[int]) -> tuple[bytes, bytes]:
    """FC 10 request and its normal answer."""
    vals = words(*values)
    return (
        encode_write_multiple_request(0x10, address, vals),
        encode_write_multiple_response(0x10, address, len(vals)),
    )


def w6(address: int, value: int) -> tuple[bytes, bytes]:
    """FC 06 request and its echo."""
    pdu = encode_write_single(0x06, address, u16(value))
    return pdu, pdu


def rd(fc: int, address: int, values: Sequence[int]) -> tuple[bytes, bytes]:
    """FC 03/04 read request and the answer carrying ``values`` (signed ok)."""
    vals = words(*values)
    return encode_read_request(fc, address, len(vals)), encode_read_response(fc, vals)


class Script:
    """Feeds (request PDU, response PDU) pairs to one session as the pairing stage would."""

    def __init__(
        self, session: HrssSession | None = None, t0: float = 1000.0, step: float = 0.05
    ) -> None:
        self.session = session or HrssSession(STREAM, 1)
        self.t = t0
        self.step = step
        self.tid = 0
        self.log: list[tuple[Annotation, Annotation | None]] = []

    def frame(self, pdu: bytes, direction: Direction, *, request: Frame | None = None) -> Frame:
        resp = direction is Direction.S2C
        decoded = decode_pdu(pdu, resp, request=request.pdu if request else None)
        mbap = self.tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big")
        return Frame(self.t, STREAM, direction, 1, self.tid, decoded, mbap + b"\x01" + pdu)

    def __call__(
        self,
        pair: tuple[bytes, bytes | None],
        *,
        dt: float | None = None,
        latency: float = 0.004,
    ) -> tuple[Annotation, Annotation | None]:
        """One request (PENDING) and its answer (ANSWERED/EXCEPTION, None = no answer)."""
        req_pdu, resp_pdu = pair
        self.t += self.step if dt is None else dt
        self.tid += 1
        req = self.frame(req_pdu, Direction.C2S)
        a1 = self.session.feed(Transaction(self.t, TxStatus.PENDING, req, None))
        a2 = None
        if resp_pdu is not None:
            t_req = self.t
            self.t += latency
            resp = self.frame(resp_pdu, Direction.S2C, request=req)
            status = TxStatus.EXCEPTION if resp_pdu[0] & 0x80 else TxStatus.ANSWERED
            a2 = self.session.feed(Transaction(self.t, status, req, resp, self.t - t_req))
        self.log.append((a1, a2))
        return a1, a2

    def run(self, pairs: Sequence[tuple[bytes, bytes | None]]) -> list[Annotation]:
        """Feed all pairs; every annotation in order (request's, then answer's)."""
        out: list[Annotation] = []
        for p in pairs:
            a1, a2 = self(p)
            out.append(a1)
            if a2 is not None:
                out.append(a2)
        return out


def updates(anns: Sequence[Annotation | None]) -> list[CommandUpdate]:
    return [c for a in anns if a is not None for c in a.commands]


def phases(anns: Sequence[Annotation | None]) -> list[Phase]:
    return [c.phase for c in updates(anns)]


def notes(anns: Sequence[Annotation | None]) -> list[str]:
    return [n for a in anns if a is not None for n in a.notes]


def warnings(anns: Sequence[Annotation | None]) -> list[CommandUpdate]:
    return [c for c in updates(anns) if c.phase is Phase.WARNING]


def ptp_joint(
    a1: float = 90,
    speed: int = 50,
    acc: int = 100,
    tool: int = 1,
    base: int = 2,
    ext: int = 0,
    e1: float = 0,
    code: int = 0,
) -> list[int]:
    """R201..R226 of a PTP in joint coordinates (Table 17), as unsigned words."""
    return (
        words(0, 0)
        + i32(a1)
        + [0] * 10
        + words(speed, acc, tool, base, ext)
        + i32(e1)
        + [0] * 4
        + words(code)
    )


# --------------------------------------------------------------------------- data (Table 16)

# Table 16: parameter registers (holding) and return registers (input) per command.
# Set Home Position: Table 16 says 1, Table 31 lists A1..A6 in R202..R213 (12): Table 31 wins.
TABLE_16 = {
    0: ("PTP", 25, None), 1: ("LIN", 25, None), 2: ("CIRC", 36, None), 3: ("JOG", 2, None),
    4: ("GO HOME", 1, None), 5: ("T_STOP", 2, None), 6: ("Motion Stop", 0, None),
    100: ("Set PR", 14, None), 101: ("Set TOOL", 13, None), 102: ("Set BASE", 13, None),
    103: ("Set Current TOOL", 1, None), 104: ("Set Current BASE", 1, None),
    105: ("Set HOME", 12, None), 200: ("Get PR", 1, 14), 201: ("Get TOOL", 1, 13),
    202: ("Get BASE", 1, 13), 203: ("Get Current TOOL", 0, 1), 204: ("Get Current BASE", 0, 1),
    205: ("Get HOME", 0, 12),
}  # fmt: skip


def test_every_command_of_table_16_with_its_register_counts() -> None:
    spec = load_spec()
    assert set(spec.commands) == set(TABLE_16)
    for code, (name, n_params, n_returns) in TABLE_16.items():
        cmd = spec.commands[code]
        assert cmd.name == name
        widest = max(len(cmd.params.regs(lay)) for lay in cmd.params.layouts)
        assert widest == n_params, name
        assert all(min(cmd.params.regs(lay), default=202) >= 202 for lay in cmd.params.layouts)
        if n_returns is None:
            assert cmd.returns is None
        else:
            assert cmd.returns is not None
            assert max(len(cmd.returns.regs(lay)) for lay in cmd.returns.layouts) == n_returns


def test_no_layout_has_overlapping_fields() -> None:
    for cmd in load_spec().commands.values():
        for form in (cmd.params, cmd.returns):
            for lay in form.layouts if form else ():
                regs = [r for f in lay.fields for r in f.regs]
                if form.select is not None:
                    regs += list(form.select.regs)
                assert len(regs) == len(set(regs)), (cmd.name, lay.table)


@pytest.mark.parametrize(
    ("raw", "decimals", "text"),
    [
        (90830, 3, "90.83"), (90000, 3, "90"), (-399958, 3, "-399.958"), (0, 3, "0"),
        (-1, 3, "-0.001"), (-300000, 3, "-300"), (5, 0, "5"), (-5, 0, "-5"), (4600, 2, "46"),
    ],
)  # fmt: skip
def test_numbers_are_printed_without_trailing_zeros(raw: int, decimals: int, text: str) -> None:
    assert format_scaled(raw, decimals) == text


# --------------------------------------------------------------------------- text forms


def holding(first: int, values: Sequence[int]) -> dict[int, int]:
    return {first + i: v for i, v in enumerate(words(*values))}


@pytest.mark.parametrize(
    ("regs", "text"),
    [
        (holding(201, ptp_joint()), "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% "
         "TOOL[1] BASE[2]"),
        (holding(201, ptp_joint(ext=1, e1=-12.5, code=-7)),
         "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0, E1 -12.5, E2 0, E3 0} Vel=50% Acc=100% "
         "TOOL[1] BASE[2] Code=-7"),
        (holding(201, [0, 1, *i32(-300), *i32(300), *i32(400), *i32(180), 0, 0, *i32(90),
                       10, 20, 3, 7, 0]),
         "PTP {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=10% Acc=20% TOOL[3] BASE[7]"),
        (holding(201, [0, 2, 12] + [0] * 11 + [50, 100, 0, 0]),
         "PTP $PR[12] Vel=50% Acc=100% TOOL[0] BASE[0]"),
        (holding(201, [1, 2, 12] + [0] * 11 + [800, 100, 0, 0, 1, *i32(1.5), 0, 0, 0, 0, 9]),
         "LIN $PR[12] {E1 1.5, E2 0, E3 0} Vel=800mm/s Acc=100% TOOL[0] BASE[0] Code=9"),
        (holding(201, [1, 0, *i32(-0.001)] + [0] * 10 + [100, 50, 1, 1, 0]),
         "LIN {A1 -0.001, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=100mm/s Acc=50% TOOL[1] BASE[1]"),
        (holding(201, [2, *i32(10), *i32(20), *i32(30), *i32(180), 0, 0, *i32(-90),
                       *i32(40), *i32(50), *i32(60), *i32(180), 0, 0, *i32(0.25),
                       250, 80, 2, 3, 0]),
         "CIRC {X 10, Y 20, Z 30, A 180, B 0, C -90} {X 40, Y 50, Z 60, A 180, B 0, C 0.25} "
         "Vel=250mm/s Acc=80% TOOL[2] BASE[3]"),
        (holding(201, [3, 8, -1]), "JOG Z -"),
        (holding(201, [3, 14, 0]), "JOG E3 stop"),
        (holding(201, [4, 1]), "GO HOME"),
        (holding(201, [4, 0]), "GO HOME stop"),
        (holding(201, [5, 3, 1]), "T_STOP Timer[3]"),
        (holding(201, [5, 3, 0]), "T_STOP Timer[3] FALSE"),
        (holding(201, [6]), "Motion Stop"),
        (holding(201, [100, 4000, 1, *i32(1), *i32(2), *i32(3), *i32(4), *i32(5), *i32(6)]),
         "$PR[4000] = {A1 1, A2 2, A3 3, A4 4, A5 5, A6 6}"),
        (holding(201, [100, 7, 0]), "$PR[7] = NULL"),
        (holding(201, [101, 1, *i32(0), *i32(0), *i32(125.5), *i32(0), *i32(0), *i32(0)]),
         "Set TOOL[1] = {X 0, Y 0, Z 125.5, A 0, B 0, C 0}"),
        (holding(201, [102, 31, *i32(500), *i32(-20), *i32(0), *i32(0), *i32(0), *i32(45)]),
         "Set BASE[31] = {X 500, Y -20, Z 0, A 0, B 0, C 45}"),
        (holding(201, [103, 15]), "Set Current TOOL[15]"),
        (holding(201, [104, 0]), "Set Current BASE[0]"),
        (holding(201, [105, *i32(0), *i32(-90), *i32(90), *i32(0), *i32(0), *i32(0)]),
         "Set HOME {A1 0, A2 -90, A3 90, A4 0, A5 0, A6 0}"),
        (holding(201, [200, 2]), "Get PR[2]"),
        (holding(201, [201, 4]), "Get TOOL[4]"),
        (holding(201, [202, 6]), "Get BASE[6]"),
        (holding(201, [203]), "Get Current TOOL"),
        (holding(201, [204]), "Get Current BASE"),
        (holding(201, [205]), "Get HOME"),
        (holding(201, [0, 0]), "PTP {A1 ?, A2 ?, A3 ?, A4 ?, A5 ?, A6 ?} Vel=?% Acc=?% TOOL[?] "
         "BASE[?]"),
        (holding(201, [0, 7]), "PTP (point type 7)"),
        (holding(201, [77]), "unknown command 77"),
        ({}, "command ? (R201 never seen)"),
    ],
)  # fmt: skip
def test_command_text_in_hrss_program_form(regs: dict[int, int], text: str) -> None:
    assert decode_command(regs).text == text


def test_range_problems_name_field_value_range_and_registers() -> None:
    regs = holding(201, ptp_joint(speed=201, acc=0, tool=16, base=32))
    assert decode_command(regs).problems == (
        "speed 201 outside 1..200 (R215)",
        "acc 0 outside 1..100 (R216)",
        "tool 16 outside 0..15 (R217)",
        "base 32 outside 0..31 (R218)",
    )
    assert decode_command(holding(201, ptp_joint(speed=200, acc=1, base=31))).problems == ()
    lin = holding(201, [1, 2, 4001] + [0] * 11 + [6001, 100, 0, 0, 0])
    assert decode_command(lin).problems == (
        "pr 4001 outside 1..4000 (R203)",
        "speed 6001 outside 1..6000 (R215)",
    )
    assert decode_command(holding(201, [0, 3])).problems == ("point_type 3 outside 0..2 (R202)",)
    unknown = decode_command(holding(201, [7]))
    assert unknown.problems == ("command number 7 not in Table 16 (R201)",)


@pytest.mark.parametrize(
    ("code", "regs", "text"),
    [
        (201, holding(202, [4, *i32(1), *i32(2), *i32(3), *i32(4), *i32(5), *i32(6)]),
         "TOOL[4] = {X 1, Y 2, Z 3, A 4, B 5, C 6}"),
        (202, holding(202, [6, *i32(-1), *i32(0), *i32(0), *i32(0), *i32(0), *i32(-179.999)]),
         "BASE[6] = {X -1, Y 0, Z 0, A 0, B 0, C -179.999}"),
        (203, holding(202, [3]), "Current TOOL = TOOL[3]"),
        (204, holding(202, [7]), "Current BASE = BASE[7]"),
        (205, holding(202, [*i32(0), *i32(-90), *i32(90), *i32(0), *i32(90), *i32(0)]),
         "HOME = {A1 0, A2 -90, A3 90, A4 0, A5 90, A6 0}"),
        (200, holding(202, [9, 1, *i32(90.83), *i32(0), *i32(0), *i32(0), *i32(0), *i32(0)]),
         "PR[9] = {A1 90.83, A2 0, A3 0, A4 0, A5 0, A6 0}"),
        (200, holding(202, [9, 0]), "PR[9] = NULL"),
    ],
)  # fmt: skip
def test_get_returns_decoded_per_tables_33_to_43(
    code: int, regs: dict[int, int], text: str
) -> None:
    dec = decode_returns(code, regs)
    assert dec is not None and dec.text == text and not dec.missing


def test_commands_without_returns_have_none() -> None:
    assert decode_returns(0, {}) is None
    assert decode_returns(100, {}) is None


@settings(max_examples=200, deadline=None)
@given(
    st.integers(-(2**31), 2**31 - 1),
    st.integers(-(2**31), 2**31 - 1),
    st.integers(1, 6000),
)
def test_any_32_bit_pose_round_trips_through_the_words(x: int, c: int, vel: int) -> None:
    regs = holding(201, [1, 1])
    for reg, v in ((203, x), (213, c)):
        lo, hi = split_i32(v)
        regs[reg], regs[reg + 1] = u16(lo), u16(hi)
    for reg in (205, 206, 207, 208, 209, 210, 211, 212):
        regs[reg] = 0
    regs.update(holding(215, [vel, 100, 0, 0, 0]))
    dec = decode_command(regs)
    assert dec.text == (
        f"LIN {{X {format_scaled(x, 3)}, Y 0, Z 0, A 0, B 0, C {format_scaled(c, 3)}}} "
        f"Vel={vel}mm/s Acc=100% TOOL[0] BASE[0]"
    )
    assert dec.params["X"] == pytest.approx(x / 1000, abs=1e-9)
    assert dec.problems == ()


# --------------------------------------------------------------------------- lifecycle


def test_written_once_per_block_across_several_requests_then_executing_and_success() -> None:
    s = Script()
    block = ptp_joint()
    a_first, _ = s(wr(201, block[:10]))
    a_second, _ = s(wr(211, block[10:]))
    a_again, _ = s(wr(215, [60]))  # a change after the block was complete: no second WRITTEN
    assert phases([a_first]) == []
    assert phases([a_second]) == [Phase.WRITTEN]
    assert phases([a_again]) == []
    text = "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2]"
    assert updates([a_second])[0].text == text
    assert notes([a_second]) == [f"written: {text}"]
    ex, ok = s(w6(200, 1))
    execute = updates([ex])
    text60 = text.replace("Vel=50%", "Vel=60%")
    assert [(c.phase, c.text, c.code) for c in execute] == [(Phase.EXECUTING, text60, 0)]
    assert notes([ex]) == [f"execute: {text60}"]
    assert execute[0].params["A1"] == 90 and execute[0].params["speed"] == 60
    assert ok is not None and ok.commands == ()
    t_exec = execute[0].ts
    _, pending = s(rd(0x04, 200, [0, 0]), dt=0.2)
    assert pending is not None and pending.commands == ()
    _, done = s(rd(0x04, 200, [1, 0]), dt=0.3)
    [success] = updates([done])
    assert success.phase is Phase.SUCCESS and success.text == text60
    assert success.duration == pytest.approx(success.ts - t_exec)
    assert success.duration == pytest.approx(0.004 + 0.2 + 0.004 + 0.3 + 0.004)
    assert success.params["status"] == 1 and success.params["action"] == 0
    assert notes([done]) == [f"success: {text60} ({success.duration:.3f} s)"]
    _, again = s(rd(0x04, 200, [1, 0]))
    assert again is not None and again.commands == ()  # one final status per execute
    reset, _ = s(w6(200, 0))
    assert reset.commands == () and reset.notes == ()


def test_fail_status_and_no_returns_after_a_failed_get() -> None:
    s = Script()
    s(wr(201, [200, 2]))
    s(w6(200, 1))
    _, failed = s(rd(0x04, 200, [2, 200, 2, 2, *i32(90), *([0] * 10)]))
    assert phases([failed]) == [Phase.FAIL]
    assert notes([failed])[0].startswith("fail: Get PR[2] (")


def test_execute_without_reset_warns() -> None:
    s = Script()
    s(wr(201, [6]))
    first, _ = s(w6(200, 1))
    assert phases([first]) == [Phase.EXECUTING]
    s(wr(201, [4, 1]))
    second, _ = s(w6(200, 1))
    assert phases([second]) == [Phase.WARNING, Phase.EXECUTING]
    [warn] = warnings([second])
    assert warn.params["warning"] == "no_reset" and warn.code == 4
    assert warn.text == (
        "execute without reset: R200 was still 1 when GO HOME was executed "
        "(reset R200 = 0 first, §5.3.3.5)"
    )
    assert notes([second])[0] == f"warning: {warn.text}"
    s(w6(200, 0))
    third, _ = s(w6(200, 1))
    assert phases([third]) == [Phase.EXECUTING]  # reset seen: no warning


def test_r200_unknown_before_execute_is_not_a_missing_reset() -> None:
    s = Script()
    s(wr(201, [6]))
    ex, _ = s(wr(200, [1]))
    assert phases([ex]) == [Phase.EXECUTING]


def test_out_of_range_parameters_warn_once_at_execute() -> None:
    s = Script()
    written, _ = s(wr(201, ptp_joint(speed=250, tool=20)))
    assert phases([written]) == [Phase.WRITTEN]  # no warning while only written
    ex, _ = s(w6(200, 1))
    assert phases([ex]) == [Phase.EXECUTING, Phase.WARNING]
    [warn] = warnings([ex])
    assert warn.params["warning"] == "range"
    assert warn.text.endswith(": speed 250 outside 1..200 (R215); tool 20 outside 0..15 (R217)")


def test_r200_other_than_0_or_1_warns() -> None:
    s = Script()
    a, _ = s(w6(200, 2))
    assert [w.params["warning"] for w in warnings([a])] == ["range"]
    assert phases([a]) == [Phase.WARNING]


def test_never_completes_after_the_timeout_while_the_client_polls_ir200() -> None:
    s = Script(HrssSession(STREAM, 1, complete_timeout=2.0))
    s(wr(201, [100, 3, 2, *i32(1), *([0] * 10)]))
    s(w6(200, 1))
    quiet = [s(rd(0x04, 200, [0]), dt=0.5) for _ in range(3)]  # 1.5 s: still in time
    assert warnings([a for pair in quiet for a in pair]) == []
    late_req, _ = s(rd(0x04, 200, [0]), dt=0.6)
    [warn] = warnings([late_req])  # the first frame past the deadline carries it
    assert warn.params["warning"] == "never_completed" and warn.code == 100
    assert warn.text == (
        "never completed: $PR[3] = {X 1, Y 0, Z 0, A 0, B 0, C 0} "
        "(no IR200 status 2 s after R200 = 1)"
    )
    more = [s(rd(0x04, 200, [0]), dt=1.0) for _ in range(3)]
    assert warnings([a for pair in more for a in pair]) == []  # said once


def test_no_never_completes_when_the_client_never_looks_or_the_status_comes() -> None:
    s = Script(HrssSession(STREAM, 1, complete_timeout=1.0))
    s(wr(201, [6]))
    s(w6(200, 1))
    blind = [s(rd(0x04, 300, [0] * 12), dt=0.5) for _ in range(6)]  # 3 s of position polls
    assert warnings([a for pair in blind for a in pair]) == []
    s(w6(200, 0))
    s(w6(200, 1))
    s(rd(0x04, 200, [0]), dt=0.5)
    _, ok = s(rd(0x04, 200, [1]), dt=0.4)
    assert phases([ok]) == [Phase.SUCCESS]
    after = [s(rd(0x04, 200, [1]), dt=1.0) for _ in range(3)]
    assert warnings([a for pair in after for a in pair]) == []


def test_never_completes_when_the_next_execute_comes_after_polls_without_status() -> None:
    s = Script()
    s(wr(201, [6]))
    s(w6(200, 1))
    s(rd(0x04, 200, [0]))
    s(w6(200, 0))
    s(wr(201, [4, 1]))
    nxt, _ = s(w6(200, 1))
    assert phases([nxt]) == [Phase.WARNING, Phase.EXECUTING]
    [warn] = warnings([nxt])
    assert warn.params["warning"] == "never_completed" and warn.code == 6
    assert warn.text.startswith("never completed: Motion Stop (no IR200 status before the next")


def test_hold_to_run_jog_does_not_time_out_and_reset_stops_it() -> None:
    s = Script(HrssSession(STREAM, 1, complete_timeout=1.0))
    s(wr(201, [3, 0, 1]))
    s(w6(200, 1))
    polls = [s(rd(0x04, 200, [0]), dt=0.5) for _ in range(6)]
    assert warnings([a for pair in polls for a in pair]) == []
    stop, _ = s(w6(200, 0))
    assert notes([stop]) == ["stop: JOG A1 + (R200 = 0 after 3.078 s)"]
    later = [s(rd(0x04, 200, [0]), dt=1.0) for _ in range(2)]
    assert warnings([a for pair in later for a in pair]) == []


def test_queue_above_8000_warns_once_per_crossing() -> None:
    s = Script()
    anns = [s(rd(0x04, 102, [q]))[1] for q in (8000, 8001, 8100, 7999, 8050)]
    assert [len(warnings([a])) for a in anns] == [0, 1, 0, 0, 1]
    [w] = warnings([anns[1]])
    assert w.text == "8001 commands queued (IR102 > 8000): motion commands will fail"
    assert w.params["warning"] == "queue"
    assert s.session.state["queued"] == 8050


def test_exception_answer_puts_the_old_values_back_and_rejects_the_execute() -> None:
    s = Script()
    s(wr(201, [104, 3]))
    _, rej = s((encode_write_multiple_request(0x10, 201, [103, 9]), encode_exception(0x10, 2)))
    assert notes([rej]) == ["write rejected (exception 2): R201..R202 unchanged"]
    assert s.session.holding[201] == 104 and s.session.holding[202] == 3
    assert s.session.unconfirmed == frozenset()
    ex, rej2 = s((encode_write_single(0x06, 200, 1), encode_exception(0x06, 4)))
    assert phases([ex]) == [Phase.EXECUTING]
    assert [w.params["warning"] for w in warnings([rej2])] == ["rejected"]
    assert warnings([rej2])[0].text == "execute rejected (exception 4): Set Current BASE[3]"
    assert 200 not in s.session.holding
    again, _ = s(w6(200, 1))  # the rejected execute left R200 as it was: no missing reset
    assert phases([again]) == [Phase.EXECUTING]


def test_writes_are_unconfirmed_until_answered_and_stay_so_on_timeout() -> None:
    s = Script()
    s((encode_write_single(0x06, 217, 5), None))
    assert s.session.holding[217] == 5 and s.session.unconfirmed == {217}
    s(w6(218, 6))
    assert s.session.unconfirmed == {217}


def test_fc17_writes_and_reads_and_fc16_mask_write_update_the_image() -> None:
    s = Script()
    # 0x17: read IR? no: holding 100..101, write R201..R202 = Get Current BASE (no params)
    req = bytes.fromhex("17 0064 0002 00C9 0001 02 00CC".replace(" ", ""))
    a, _ = s((req, encode_read_response(0x17, [90, 0])))
    assert [(c.phase, c.text) for c in updates([a])] == [(Phase.WRITTEN, "Get Current BASE")]
    assert s.session.holding[100] == 90 and s.session.holding[201] == 204
    s(w6(300, 0x00F0))
    mask = bytes.fromhex("16012C00FF0001")  # (0x00F0 & 0x00FF) | (0x0001 & ~0x00FF)
    s((mask, mask))
    assert s.session.holding[300] == 0x00F0
    s((bytes.fromhex("16012D00FF0001"), bytes.fromhex("16012D00FF0001")))
    assert 301 not in s.session.holding  # old value unknown: result unknown


def test_holding_reads_fill_the_image_used_at_execute() -> None:
    s = Script()
    s(rd(0x03, 201, ptp_joint(a1=-45.5)))  # the client reads back what is there
    ex, _ = s(w6(200, 1))
    assert updates([ex])[0].text.startswith("PTP {A1 -45.5, A2 0,")


def test_other_unit_is_ignored() -> None:
    session = HrssSession(STREAM, 2)
    s = Script(session)
    a, b = s(wr(201, [6]))
    assert a == Annotation() and b == Annotation()
    assert session.holding == {}


def test_state_is_returned_only_when_it_changes() -> None:
    s = Script()
    _, first = s(rd(0x04, 520, [*i32(123.456), 1, 250, 2]))
    assert first is not None and first.state == {
        "tcp_speed": 123.456,
        "excitation": 1.0,
        "acc_time": 0.25,
        "motion_state": 2.0,
    }
    _, same = s(rd(0x04, 520, [*i32(123.456), 1, 250, 2]))
    assert same is not None and same.state is None
    _, err = s(rd(0x04, 500, words(0x0001, 0x0A20, -1, -1)))
    assert err is not None and err.state is not None
    assert err.state["error_drive"] == 0x0A200001 and err.state["error_hrss"] == 0xFFFFFFFF
    assert s.session.state["tcp_speed"] == 123.456


def test_motion_state_changes_are_noted() -> None:
    s = Script()
    got = [s(rd(0x04, 524, [v]))[1] for v in (1, 1, 2, 3, 1)]
    assert [notes([a]) for a in got] == [
        ["motion: Idle (1)"],
        [],
        ["motion: Idle (1) -> Running (2)"],
        ["motion: Running (2) -> Hold (3)"],
        ["motion: Hold (3) -> Idle (1)"],
    ]


# --------------------------------------------------------------------------- time alone (ticks)


def test_never_completes_on_time_while_the_line_is_silent() -> None:
    """Execute, one IR200 poll (not done yet), then only ticks: the warning is on time."""
    session = HrssSession(STREAM, 1, complete_timeout=2.0)
    s = Script(session)
    s(wr(201, [100, 3, 2, *i32(1), *([0] * 10)]))
    assert session.next_deadline() is None  # nothing executed: no deadline
    ex, _ = s(w6(200, 1))
    t_exec = updates([ex])[0].ts
    assert session.next_deadline() is None  # nobody looked at the status yet
    s(rd(0x04, 200, [0]), dt=0.1)
    deadline = session.next_deadline()
    assert deadline is not None and deadline == pytest.approx(t_exec + 2.0)
    assert session.tick(t_exec + 1.0) == []
    assert session.tick(deadline - 1e-6) == []
    [warn] = session.tick(deadline)
    assert warn.phase is Phase.WARNING and warn.ts == deadline
    assert warn.params["warning"] == "never_completed" and warn.code == 100
    assert warn.stream == STREAM and warn.unit == 1
    assert warn.text == (
        "never completed: $PR[3] = {X 1, Y 0, Z 0, A 0, B 0, C 0} "
        "(no IR200 status 2 s after R200 = 1)"
    )
    assert session.next_deadline() is None  # said once
    assert session.tick(deadline + 10) == []
    late, _ = s(rd(0x04, 200, [0]), dt=5.0)
    assert warnings([late]) == []  # a later transaction does not repeat it


def test_ticks_say_nothing_when_the_status_came_or_nobody_looked() -> None:
    session = HrssSession(STREAM, 1, complete_timeout=1.0)
    s = Script(session)
    s(wr(201, [6]))
    s(w6(200, 1))
    assert session.next_deadline() is None and session.tick(s.t + 5.0) == []  # never looked
    s(w6(200, 0))
    s(w6(200, 1))
    s(rd(0x04, 200, [0]), dt=0.2)
    assert session.next_deadline() is not None
    _, ok = s(rd(0x04, 200, [1]), dt=0.2)
    assert phases([ok]) == [Phase.SUCCESS]
    assert session.next_deadline() is None and session.tick(s.t + 5.0) == []


def test_ticks_wait_while_hold_to_run_is_held() -> None:
    session = HrssSession(STREAM, 1, complete_timeout=1.0)
    s = Script(session)
    s(wr(201, [3, 0, 1]))
    s(w6(200, 1))
    s(rd(0x04, 200, [0]), dt=0.2)
    assert session.next_deadline() is None and session.tick(s.t + 5.0) == []  # JOG held


def test_unanswered_writes_are_bounded_and_the_oldest_dropped_with_a_note() -> None:
    session = HrssSession(STREAM, 1, max_writes=4)
    s = Script(session)
    notes = [s((w6(300 + i, i)[0], None))[0].notes for i in range(6)]  # never answered
    assert notes[:4] == [(), (), (), ()]
    assert notes[4] == (
        "warning: more than 4 writes unanswered: the oldest (R300) is forgotten, "
        "its values stay unconfirmed",
    )
    assert "(R301)" in notes[5][0]
    assert session.unconfirmed == frozenset(range(300, 306))
    assert len(session._writes) == 4


def test_annotator_ticks_reach_the_hrss_sessions() -> None:
    from mbmon.semantics.annotate import Annotator
    from mbmon.semantics.profile import ProfileBinding

    a = Annotator(ProfileBinding.parse(["hrss"]))
    assert a.next_deadline() is None and a.tick(5.0) == []

    class Fed:  # the annotator takes pairing steps as the session does
        def feed(self, tx: Transaction) -> Annotation:
            return a.annotate(tx)

    s = Script()
    s.session = Fed()  # type: ignore[assignment]
    s(wr(201, [6]))
    s(w6(200, 1))
    s(rd(0x04, 200, [0]))
    deadline = a.next_deadline()
    assert deadline is not None
    assert a.tick(deadline - 0.5) == []
    [warn] = a.tick(deadline)
    assert warn.params["warning"] == "never_completed" and warn.code == 6
    assert a.next_deadline() is None
