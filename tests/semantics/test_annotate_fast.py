"""The fast paths of ``--profile hrss`` say what the general code says (issue 10).

Each test runs generated inputs through a remembered or specialised path and
through the plain code it stands for, and wants the very same result:

* the HRSS session's remembered command decodes (:meth:`HrssSession._decode`)
  against :func:`decode_command` of the same holding image.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Stream, Transport
from mbmon.semantics.hrss import HrssSession, decode_command, load_spec

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
