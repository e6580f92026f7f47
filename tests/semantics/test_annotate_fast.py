"""The fast paths of ``--profile hrss`` say what the general code says.

Each test runs generated inputs through a remembered or specialised path and
through the plain code it stands for, and wants the very same result:

* the HRSS session's remembered command decodes (:meth:`HrssSession._decode`)
  against :func:`decode_command` of the same holding image;
* the session's input image, whose FC 04 answers are applied only when it is
  read, against every answer applied in turn;
* the annotator's polling path (a read request's meaning and its answer's
  layout, kept by the request's bytes) against the general notes of a frame
  (:meth:`Annotator._frame_notes`), selector memory included.
"""

from __future__ import annotations

import dataclasses

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Direction, Frame, Stream, Transaction, Transport, TxStatus
from mbmon.protocol.pdu import decode_pdu, encode_read_request, encode_read_response
from mbmon.semantics.annotate import Annotator
from mbmon.semantics.hrss import HrssSession, decode_command, load_spec
from mbmon.semantics.profile import ProfileBinding, load_profile

STREAM = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
SPEC = load_spec()

#: words that make real commands, layouts and out-of-range values, and unseen registers
_CODES = [*sorted(SPEC.commands), 99, 0xFFFF]
_WORDS = [0, 1, 2, 3, 4, 31, 0xFFFF, 0x8000, 0x5F90, 0x0001]
_WRITE = st.one_of(
    st.tuples(st.just(201), st.sampled_from([*_CODES, None])),
    st.tuples(st.integers(200, 251), st.sampled_from([*_WORDS, None])),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(_WRITE, max_size=80))
def test_remembered_decodes_are_the_decodes(writes: list[tuple[int, int | None]]) -> None:
    """After every change of the holding image, the remembered decode is decode_command's."""
    session = HrssSession(STREAM, 1)
    image = session._holding
    for reg, word in writes:
        if word is None:
            image.pop(reg, None)
        else:
            image[reg] = word
        assert session._decode() == decode_command(image, SPEC)


def _read(fc: int, address: int, words: list[int], ts: float = 1.0) -> Transaction:
    """The ANSWERED step of a read of ``words`` at ``address``."""
    rq = encode_read_request(fc, address, len(words))
    req = Frame(ts, STREAM, Direction.C2S, 1, 1, decode_pdu(rq, False), rq)
    rs = encode_read_response(fc, words)
    resp = Frame(ts, STREAM, Direction.S2C, 1, 1, decode_pdu(rs, True, req.pdu), rs)
    return Transaction(ts, TxStatus.ANSWERED, req, resp, 0.0)


_ANSWER = st.one_of(
    # a few shapes over and over (polling), overlapping one another
    st.tuples(
        st.sampled_from([200, 201, 300, 305, 500, 520]),
        st.sampled_from([1, 2, 5, 24]).flatmap(
            lambda n: st.lists(st.integers(0, 0xFFFF), min_size=n, max_size=n)
        ),
        st.booleans(),  # read the image after this answer
    ),
    # any shape: more shapes than are kept unapplied
    st.tuples(
        st.integers(0, 700),
        st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=30),
        st.booleans(),
    ),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(_ANSWER, max_size=150))
def test_input_image_is_every_answer_applied_in_turn(
    answers: list[tuple[int, list[int], bool]],
) -> None:
    """Any answers, any overlaps, read at any time: the image (and a view kept from the start)."""
    session = HrssSession(STREAM, 1)
    view = session.inputs
    expected: dict[int, int] = {}
    for address, words, look in answers:
        session.feed(_read(4, address, words))
        expected.update(zip(range(address, address + len(words)), words, strict=True))
        if look:
            assert dict(session.inputs) == expected
    assert dict(view) == expected and len(view) == len(expected)
    assert dict(session.inputs) == expected


def _annotators() -> tuple[Annotator, Annotator]:
    """Two annotators of the HRSS and XEG register maps without the session (its notes
    would come after the profile's on both paths alike): one per path."""
    bound = [
        ("hrss", dataclasses.replace(load_profile("hrss"), session=None)),
        ("unit:2=xeg", load_profile("xeg")),
    ]
    return (
        Annotator(ProfileBinding.from_profiles(bound)),
        Annotator(ProfileBinding.from_profiles(bound)),
    )


#: (fc, address, count): polling shapes, the PR[n] groups (selectors), XEG, anything
_POLLED = st.sampled_from([200, 300, 500, 520, 1000, 1019])
_PR = st.sampled_from([1000, 1001, 1003, 1019, 1020])  # PR[1], PR[2]: with and without type
_SHAPE = st.one_of(
    st.tuples(st.sampled_from([3, 4]), _POLLED, st.integers(1, 40)),
    st.tuples(st.just(3), _PR, st.sampled_from([2, 4, 5, 19])),
    st.tuples(st.just(3), st.integers(995, 1300), st.integers(1, 125)),
    st.tuples(st.sampled_from([1, 2]), st.integers(0, 600), st.integers(1, 40)),
    st.tuples(st.sampled_from([3, 4]), st.integers(760, 1610), st.integers(1, 20)),
    st.tuples(st.integers(1, 4), st.integers(0, 0xFFFF), st.integers(1, 200)),
)
#: (shape, unit, values shown beyond or short of the count, words, answered with another fc,
#: the request was seen): small words make PR[n].type pick its variants
_POLL = st.tuples(
    _SHAPE,
    st.sampled_from([1, 1, 1, 2]),
    st.sampled_from([0, 0, 0, -1, 1, 3]),
    st.lists(st.one_of(st.integers(0, 3), st.integers(0, 0xFFFF)), min_size=210, max_size=210),
    st.integers(0, 9),
    st.integers(0, 5),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(_POLL, min_size=1, max_size=40))
def test_polling_notes_are_the_general_notes(
    polls: list[tuple[tuple[int, int, int], int, int, list[int], int, int]],
) -> None:
    """Request then answer, as annotate gives them and as the general frame notes do."""
    fast, general = _annotators()
    for (fc, address, count), unit, extra, words, odd, seen in polls:
        rq = encode_read_request(fc, address, count)
        req = Frame(1.0, STREAM, Direction.C2S, unit, 1, decode_pdu(rq, False), rq)
        asked = Transaction(1.0, TxStatus.PENDING, req, None)
        rfc = fc if odd else (fc % 4) + 1  # now and then answered with another read code
        n = max(1, count + extra)
        shown = [w & 1 for w in words[:n]] if rfc in (1, 2) else words[: min(n, 127)]
        rs = encode_read_response(rfc, shown)
        resp = Frame(1.1, STREAM, Direction.S2C, unit, 1, decode_pdu(rs, True), rs)
        answered = Transaction(1.1, TxStatus.ANSWERED, req, resp, 0.1)
        steps = [(asked, req), (answered, resp)] if seen else [(answered, resp)]
        for tx, frame in steps:
            profile = general.binding.for_(STREAM, unit)
            assert profile is not None
            want = tuple(general._frame_notes(tx, frame, profile))
            assert fast.annotate(tx).notes == want


def test_polling_answer_without_the_selector_reads_the_one_seen_before() -> None:
    """PR[1].type in one answer, PR[1].Value1 alone in the next: still read as A1 (°)."""
    fast, general = _annotators()
    for address, words in ((1000, [1, 5, 0, 7, 0]), (1001, [5, 0, 7, 0])):
        rq = encode_read_request(3, address, len(words))
        req = Frame(1.0, STREAM, Direction.C2S, 1, 1, decode_pdu(rq, False), rq)
        rs = encode_read_response(3, words)
        resp = Frame(1.1, STREAM, Direction.S2C, 1, 1, decode_pdu(rs, True), rs)
        fast.annotate(Transaction(1.0, TxStatus.PENDING, req, None))
        answered = Transaction(1.1, TxStatus.ANSWERED, req, resp, 0.1)
        profile = general.binding.for_(STREAM, 1)
        assert profile is not None
        assert fast.annotate(answered).notes == tuple(general._frame_notes(answered, resp, profile))
    assert fast.annotate(answered).notes[0] == "PR[1].A1 = 0.005°"


@settings(max_examples=500, deadline=None)
@given(
    k=st.integers(1, 9),
    raw=st.one_of(st.integers(-(2**31), 2**32 - 1), st.integers(-20, 20)),
    kind=st.sampled_from(["u16", "s16", "u32", "i32"]),
    unit=st.sampled_from(["", "°", "mm", "%"]),
)
def test_a_decimal_scale_gives_what_format_gives(k: int, raw: int, kind: str, unit: str) -> None:
    """A scale of exactly 10**-k is shown from the integer's digits; the text is the
    float formatting's (``format(raw * scale, ".kf")``) for every raw value a field
    can hold, signs and zero included."""
    from mbmon.semantics.values import ValueFormat, decimal_point, format_value

    scale = float(f"1e-{k}")  # as a profile's TOML gives it
    words = 1 if kind in ("u16", "s16") else 2
    bits = 16 * words
    low, high = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if kind[0] in "si" else (0, 2**bits - 1)
    raw = min(max(raw, low), high)
    u = raw & (2**bits - 1)
    values = [u] if words == 1 else [u >> 16, u & 0xFFFF]
    suffix = f" {unit}" if unit == "mm" else unit
    decimal = decimal_point(scale, f".{k}f")
    assert decimal is not None
    fmt = ValueFormat(
        type=kind, words=words, high_low=True, template="", enum=None, enum_by_value=False,
        hex=False, scale=scale, spec=f".{k}f", suffix=suffix, range=None, decimal=decimal,
    )  # fmt: skip
    assert format_value(fmt, values, 0) == format(raw * scale, f".{k}f") + suffix
    assert format_value(dataclasses.replace(fmt, decimal=None), values, 0) == (
        format(raw * scale, f".{k}f") + suffix
    )


def test_only_exact_powers_of_ten_take_the_digit_path() -> None:
    from mbmon.semantics.values import decimal_point

    assert decimal_point(0.001, ".3f") == (1000, "%s%d.%03d%s")
    assert decimal_point(0.1, ".1f") == (10, "%s%d.%01d%s")
    for scale, spec in ((0.25, ".2f"), (0.005, ".3f"), (1.0, None), (10.0, None), (0.001, ".2f")):
        assert decimal_point(scale, spec) is None, scale
