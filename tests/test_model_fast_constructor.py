"""model.fast_constructor: the same objects as the dataclass constructors, made faster."""

from __future__ import annotations

import dataclasses

import pytest

from mbmon.model import (
    Chunk,
    Direction,
    Frame,
    Kind,
    Pdu,
    Record,
    RecordKind,
    Stream,
    Transaction,
    Transport,
    TxStatus,
    fast_constructor,
)

STREAM = Stream(2, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
PDU = Pdu(b"\x03\x00\x00\x00\x01", 3, Kind.REQUEST, address=0, count=1)
FRAME = Frame(1.5, STREAM, Direction.C2S, 1, 7, PDU, b"\x00\x07\x00\x00\x00\x06\x01" + PDU.raw)

EXAMPLES = [
    (Chunk, (1.5, STREAM, Direction.C2S, b"\x01\x02")),
    (Frame, (1.5, STREAM, Direction.C2S, 1, 7, PDU, FRAME.raw, None)),
    (Transaction, (1.6, TxStatus.ANSWERED, FRAME, FRAME, 0.1)),
    (
        Record,
        (4, 1.6, RecordKind.RESPONSE, STREAM, FRAME, FRAME, 3, 0.1, None, None, None, ("n",), None),
    ),
]


@pytest.mark.parametrize(("cls", "values"), EXAMPLES, ids=lambda x: getattr(x, "__name__", ""))
def test_same_object_as_the_class_makes(cls: type, values: tuple) -> None:
    made = fast_constructor(cls)(*values)
    assert type(made) is cls
    assert made == cls(*values)
    assert repr(made) == repr(cls(*values))
    assert all(  # every slot holds the very object given
        getattr(made, f.name) is value
        for f, value in zip(dataclasses.fields(cls), values, strict=True)
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        made.ts = 0.0  # type: ignore[misc]


def test_every_field_is_required() -> None:
    with pytest.raises(TypeError):
        fast_constructor(Record)(0, 1.0, RecordKind.REQUEST, STREAM)


def test_only_frozen_slotted_dataclasses() -> None:
    @dataclasses.dataclass(slots=True)
    class Mutable:
        x: int

    @dataclasses.dataclass(frozen=True)
    class NoSlots:
        x: int

    @dataclasses.dataclass(frozen=True, slots=True)
    class PostInit:
        x: int

        def __post_init__(self) -> None:
            pass

    for cls in (Mutable, NoSlots, PostInit, int):
        with pytest.raises(TypeError):
            fast_constructor(cls)
