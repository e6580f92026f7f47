"""The worked examples of manual §5.3.3.7 (Examples 1-9, Tables 44-53) and Appendix II, on the wire.

Each example is a byte table: (request PDU, response PDU) in hex, function code
first, as the robot's Modbus Monitor would show them (§5.5). The requests are
the ones the example describes: FC 10 to R201.. with the table's values, then
FC 06 R200 = 1, the IR200 status read with a realistic answer, FC 06 R200 = 0.
"""

from __future__ import annotations

import pytest
from test_hrss_commands import (
    Script,
    notes,
    phases,
    updates,
    warnings,
    words,
)

from mbmon.model import Phase
from mbmon.protocol.pdu import encode_write_multiple_request


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def table(rows: list[tuple[str, str | None]]) -> list[tuple[bytes, bytes | None]]:
    return [(h(q), h(r) if r is not None else None) for q, r in rows]


EXECUTE = ("06 00C8 0001", "06 00C8 0001")  # R200 = 1
RESET = ("06 00C8 0000", "06 00C8 0000")  # R200 = 0
STATUS_OK = ("04 00C8 0002", "04 04 0001 0000")  # IR200 = 1 success, IR201 = 0 (PTP)

# ---------------------------------------------------------------- Example 3 (Table 46, Table 17)

EXAMPLE_3 = [
    (
        "10 00C9 001A 34"
        " 0000 0000 5F90 0001 0000 0000 0000 0000 0000 0000 0000 0000 0000 0000"  # R201..R214
        " 0032 0064 0001 0002 0000 0000 0000 0000 0000 0000 0000 0000",  # R215..R226
        "10 00C9 001A",
    ),
    EXECUTE,
    STATUS_OK,
    RESET,
]
TABLE_46 = {
    201: 0, 202: 0, 203: 24464, 204: 1, 205: 0, 206: 0, 207: 0, 208: 0, 209: 0, 210: 0,
    211: 0, 212: 0, 213: 0, 214: 0, 215: 50, 216: 100, 217: 1, 218: 2, 219: 0, 220: 0,
    221: 0, 222: 0, 223: 0, 224: 0, 225: 0, 226: 0,
}  # fmt: skip
PTP_3 = "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2]"


def test_example_3_byte_table_is_table_46() -> None:
    assert h(EXAMPLE_3[0][0]) == encode_write_multiple_request(0x10, 201, words(*TABLE_46.values()))


def test_example_3_ptp_in_joint_coordinates() -> None:
    s = Script()
    write, write_ok, ex, ex_ok, st_req, st, reset, reset_ok = s.run(table(EXAMPLE_3))
    assert [(c.phase, c.text, c.code) for c in write.commands] == [(Phase.WRITTEN, PTP_3, 0)]
    assert write.notes == (f"written: {PTP_3}",)
    assert [(c.phase, c.text, c.code) for c in ex.commands] == [(Phase.EXECUTING, PTP_3, 0)]
    assert ex.notes == (f"execute: {PTP_3}",)
    p = ex.commands[0].params
    assert (p["point_type"], p["A1"], p["speed"], p["acc"], p["tool"], p["base"]) == (
        0, 90, 50, 100, 1, 2,
    )  # fmt: skip
    [success] = st.commands
    assert success.phase is Phase.SUCCESS and success.text == PTP_3
    assert success.duration == pytest.approx(0.004 + 0.05 + 0.004)
    assert st.notes == (f"success: {PTP_3} (0.058 s)",)
    for quiet in (write_ok, ex_ok, st_req, reset, reset_ok):
        assert quiet.commands == () and quiet.notes == ()


# ---------------------------------------------------------------- Example 4 (Table 47, Table 19)

# X -300 mm = (27680, -5), Y 300 mm = (-27680, 4) as Appendix II; Z 400, A 180, C 90.
LIN_4_BODY = (
    " 6C20 FFFB 93E0 0004 1A80 0006 BF20 0002 0000 0000 5F90 0001"  # R203..R214
    " 03E8 0064 0003 0007 0000 0000 0000 0000 0000 0000 0000 0000"  # R215..R226
)
LIN_4 = "LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s Acc=100% TOOL[3] BASE[7]"


def test_example_4_lin_in_cartesian_coordinates_as_table_19_lays_it_out() -> None:
    # The example's command line and Table 19: R201 = 1 (LIN), R202 = 1 (Cartesian).
    s = Script()
    anns = s.run(table([("10 00C9 001A 34 0001 0001" + LIN_4_BODY, "10 00C9 001A"), EXECUTE]))
    assert [(c.phase, c.text, c.code) for c in updates(anns)] == [
        (Phase.WRITTEN, LIN_4, 1),
        (Phase.EXECUTING, LIN_4, 1),
    ]
    p = updates(anns)[1].params
    assert (p["X"], p["Y"], p["Z"], p["A"], p["B"], p["C"]) == (-300, 300, 400, 180, 0, 90)
    assert "execute: " + LIN_4 in notes(anns)
    assert warnings(anns) == []


def test_example_4_table_47_values_taken_literally_are_a_ptp_with_a_bad_speed() -> None:
    # Table 47 prints R201 = 0 and R202 = 0: on the wire that is a PTP in joint coordinates.
    # The session decodes what the registers say and flags Vel = 1000 % (range 1..200).
    s = Script()
    anns = s.run(table([("10 00C9 001A 34 0000 0000" + LIN_4_BODY, "10 00C9 001A"), EXECUTE]))
    ptp = "PTP {A1 -300, A2 300, A3 400, A4 180, A5 0, A6 90} Vel=1000% Acc=100% TOOL[3] BASE[7]"
    assert phases(anns) == [Phase.WRITTEN, Phase.EXECUTING, Phase.WARNING]
    assert updates(anns)[1].text == ptp
    [warn] = warnings(anns)
    assert warn.text == f"out of range in {ptp}: speed 1000 outside 1..200 (R215)"


# ---------------------------------------------------------------- Examples 5, 6 (Tables 48, 49)


def test_example_5_jog_a1_positive_runs_until_r200_is_reset() -> None:
    s = Script()
    anns = s.run(table([("10 00C9 0003 06 0003 0000 0001", "10 00C9 0003"), EXECUTE]))
    assert [(c.phase, c.text, c.code) for c in updates(anns)] == [
        (Phase.WRITTEN, "JOG A1 +", 3),
        (Phase.EXECUTING, "JOG A1 +", 3),
    ]
    stop, _ = s((h(RESET[0]), h(RESET[1])), dt=1.5)
    assert stop.notes == ("stop: JOG A1 + (R200 = 0 after 1.504 s)",)
    assert stop.commands == ()


def test_example_6_go_home_runs_until_r200_is_reset() -> None:
    s = Script()
    anns = s.run(table([("10 00C9 0002 04 0004 0001", "10 00C9 0002"), EXECUTE]))
    assert [(c.phase, c.text, c.code) for c in updates(anns)] == [
        (Phase.WRITTEN, "GO HOME", 4),
        (Phase.EXECUTING, "GO HOME", 4),
    ]
    stop, _ = s((h(RESET[0]), h(RESET[1])))
    assert stop.notes[0].startswith("stop: GO HOME (R200 = 0 after ")


# ---------------------------------------------------------------- Examples 7, 8 (Tables 50-52)

SET_PR_7 = (
    "10 00C9 000F 1E"
    " 0064 0002 0002"  # R201 = 100 Set PR, R202 = PR 2, R203 = type 2 (Cartesian)
    " 5F90 0001 0000 0000 0000 0000 0000 0000 0000 0000 0000 0000",  # X 90, Y..C 0
    "10 00C9 000F",
)
GET_PR_8 = ("10 00C9 0002 04 00C8 0002", "10 00C9 0002")  # R201 = 200 Get PR, R202 = 2
# IR200..IR215: status 1 (success), then Table 52 as printed (IR201 = 100, PR 2, type 2, X 90)
RETURNS_8 = (
    "04 00C8 0010",
    "04 20 0001 0064 0002 0002 5F90 0001 0000 0000 0000 0000 0000 0000 0000 0000 0000 0000",
)
PR_2 = "{X 90, Y 0, Z 0, A 0, B 0, C 0}"


def test_example_7_set_pr_2_cartesian() -> None:
    s = Script()
    anns = s.run(table([SET_PR_7, EXECUTE, STATUS_OK]))
    text = f"$PR[2] = {PR_2}"
    assert [(c.phase, c.text, c.code) for c in updates(anns)] == [
        (Phase.WRITTEN, text, 100),
        (Phase.EXECUTING, text, 100),
        (Phase.SUCCESS, text, 100),
    ]
    assert updates(anns)[1].params["type"] == 2 and updates(anns)[1].params["X"] == 90


def test_example_8_get_pr_2_status_and_returns_in_one_read() -> None:
    s = Script()
    s.run(table([SET_PR_7, EXECUTE, STATUS_OK, RESET]))
    anns = s.run(table([GET_PR_8, EXECUTE]))
    assert [(c.phase, c.text, c.code) for c in updates(anns)] == [
        (Phase.WRITTEN, "Get PR[2]", 200),
        (Phase.EXECUTING, "Get PR[2]", 200),
    ]
    _, ret = s((h(RETURNS_8[0]), h(RETURNS_8[1])))
    assert ret is not None
    assert [(c.phase, c.text, c.code) for c in ret.commands] == [
        (Phase.SUCCESS, "Get PR[2]", 200),
        (Phase.RETURNED, f"PR[2] = {PR_2}", 200),
    ]
    assert ret.commands[0].params["action"] == 100  # IR201 as Table 52 prints it
    assert ret.notes[1] == f"returned: PR[2] = {PR_2}"
    r = ret.commands[1].params
    assert (r["pr"], r["type"], r["X"], r["C"], r["table"]) == (2, 2, 90, 0, 33)
    _, again = s((h(RETURNS_8[0]), h(RETURNS_8[1])))
    assert again is not None and again.commands == ()  # same returns: said once


def test_example_8_returns_read_in_two_parts_after_the_status() -> None:
    s = Script()
    anns = s.run(
        table(
            [
                GET_PR_8,
                EXECUTE,
                ("04 00C8 0001", "04 02 0001"),
                ("04 00CA 0007", "04 0E 0002 0002 5F90 0001 0000 0000 0000"),  # IR202..IR208
            ]
        )
    )
    assert Phase.RETURNED not in phases(anns)
    _, rest = s((h("04 00D1 0007"), h("04 0E 0000 0000 0000 0000 0000 0000 0000")))  # ..IR215
    assert rest is not None
    assert [(c.phase, c.text) for c in rest.commands] == [(Phase.RETURNED, f"PR[2] = {PR_2}")]


def test_example_8_returns_of_another_pr_are_flagged_stale() -> None:
    s = Script()
    s.run(table([GET_PR_8, EXECUTE]))
    stale = RETURNS_8[1].replace("0002 0002 5F90", "0005 0002 5F90")  # IR202 = PR 5
    _, ret = s((h(RETURNS_8[0]), h(stale)))
    assert phases([ret]) == [Phase.SUCCESS, Phase.RETURNED, Phase.WARNING]
    assert warnings([ret])[0].text == "Get PR[2] returned PR[5]: stale returns?"


# ---------------------------------------------------------------- Example 9 (Table 53, Table 20)


def test_example_9_lin_to_position_register_written_in_two_requests() -> None:
    # Table 53 leaves R204..R214 out: a client writes R201..R203, then R215..R226.
    s = Script()
    first, _ = s((h("10 00C9 0003 06 0001 0002 0002"), h("10 00C9 0003")))
    second, _ = s(
        (
            h("10 00D7 000C 18 03E8 0064 0003 0007 0000 0000 0000 0000 0000 0000 0000 0000"),
            h("10 00D7 000C"),
        )
    )
    ex, _ = s((h(EXECUTE[0]), h(EXECUTE[1])))
    text = "LIN $PR[2] Vel=1000mm/s Acc=100% TOOL[3] BASE[7]"
    assert first.commands == ()
    assert [(c.phase, c.text) for c in second.commands] == [(Phase.WRITTEN, text)]
    assert [(c.phase, c.text, c.code) for c in ex.commands] == [(Phase.EXECUTING, text, 1)]
    assert ex.commands[0].params["pr"] == 2 and ex.commands[0].params["table"] == 20


# ---------------------------------------------------------------- Examples 1, 2 (Tables 44, 45)


def test_examples_1_and_2_coils_and_discrete_inputs_are_not_commands() -> None:
    # SI1 Start ON (coil 0), SI1..SI8 at once, coil 200 (SI201) ON, SO1..SO8 read.
    s = Script()
    anns = s.run(
        table(
            [
                ("05 0000 FF00", "05 0000 FF00"),
                ("0F 0000 0008 01 09", "0F 0000 0008"),
                ("05 00C8 FF00", "05 00C8 FF00"),
                ("02 0000 0008", "02 01 0D"),
                ("01 00C8 0001", "01 01 01"),
            ]
        )
    )
    assert updates(anns) == [] and notes(anns) == []
    assert s.session.holding == {} and s.session.inputs == {}


# ---------------------------------------------------------------- Appendix II


def test_appendix_ii_words_to_values_in_the_robot_state() -> None:
    s = Script()
    _, joints = s(
        (
            h("04 012C 000C"),  # IR300..IR311
            h("04 18 62CE 0001 0000 0000 0000 0000 0000 0000 0000 0000 0000 0000"),
        )
    )
    assert joints is not None and joints.state is not None
    assert joints.state["a1"] == 90.83  # (25294, 1): example 1 of Appendix II
    _, pose = s(
        (
            h("04 0190 000C"),  # IR400..IR411
            h("04 18 E5AA FFF9 93E0 0004 6C20 FFFB 0000 0000 0000 0000 0000 0000"),
        )
    )
    assert pose is not None and pose.state is not None
    assert pose.state["x"] == -399.958  # (-6742, -7): example 2 of Appendix II
    assert pose.state["y"] == 300  # (-27680, 4)
    assert pose.state["z"] == -300  # (27680, -5)
    assert s.session.state["a1"] == 90.83


def test_appendix_ii_a_lone_word_does_not_make_a_value() -> None:
    s = Script()
    _, low_only = s((h("04 012C 0001"), h("04 02 62CE")))  # IR300 without IR301
    assert low_only is not None and low_only.state is None
    _, high_only = s((h("04 012D 0001"), h("04 02 0001")))  # IR301 alone, a later answer
    assert high_only is not None and high_only.state is None
    assert "a1" not in s.session.state
