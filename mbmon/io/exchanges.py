"""A log as the requests a client sent and the answers it got: what replay against servers needs.

:func:`recorded_exchanges` decodes the log's ``/modbus/raw`` bytes again through
the one flow (hub, pipeline: decoders and pairing, no annotator) with the
recording's ``--timeout`` and ``--baud``, and yields one :class:`Exchange` per
recorded request, in capture order: its unit id, its PDU and the response PDU
the server gave (``None`` when it never answered). The raw bytes are the log's
lossless part, so Modbus/TCP, RTU buses and RTU over TCP give the same
exchanges, whatever the stored lines say. Responses without a request
(unsolicited) are not exchanges.

Used by :mod:`mbmon.io.emulate` (the register image) and :mod:`mbmon.io.resend`
(re-sending the requests to a live server).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from mbmon.io.mcap.reader import McapLog
from mbmon.model import Kind, Pdu, Record, RecordKind, Stream

__all__ = ["Exchange", "recorded_exchanges"]


@dataclass(frozen=True, slots=True)
class Exchange:
    """One recorded request and its answer.

    ``ts`` is the request's capture time; ``response`` is the response or
    exception PDU, ``None`` when the request timed out (or the log ends first).
    ``index`` is the request's record number in the re-decoded log.
    """

    index: int
    ts: float
    stream: Stream | None
    unit: int
    request: Pdu
    response: Pdu | None

    @property
    def exception(self) -> int | None:
        """The exception code of the answer, when the server answered with one."""
        r = self.response
        return r.exception_code if r is not None and r.kind is Kind.EXCEPTION else None


def recorded_exchanges(
    log: McapLog, keep: Callable[[Record], bool] | None = None
) -> Iterator[Exchange]:
    """Every request of the log with its answer, in the order the requests were captured.

    ``keep(request_record)`` selects requests (the replay filters'
    :meth:`~mbmon.filters.RecordFilter.matches_record`); default: every one.

    A request is yielded once its fate is known (answered, or timed out, or the
    end of the log), so the order is that of the requests, not of the answers.
    Raises :class:`~mbmon.io.mcap.reader.LogError` for a damaged log, after
    yielding every exchange before the damage.
    """
    from mbmon.hub import Hub
    from mbmon.io.replay import raw_items, recorded_options
    from mbmon.pipeline import Pipeline, PipelineConfig

    opts = recorded_options(log)
    pipeline = Pipeline(None, PipelineConfig(timeout=opts.timeout, baudrate=opts.baud))
    waiting: dict[int, Exchange | None] = {}  # request index -> exchange once answered
    order: deque[int] = deque()  # request indexes not yet yielded, in capture order
    requests: dict[int, tuple[float, Stream | None, int, Pdu]] = {}
    with Hub(pipeline) as hub:
        for record in hub.iter_records(raw_items(log)):
            kind = record.kind
            frame = record.frame
            if kind is RecordKind.REQUEST and frame is not None:
                if keep is not None and not keep(record):
                    continue
                requests[record.index] = (record.ts, record.stream, frame.unit, frame.pdu)
                waiting[record.index] = None
                order.append(record.index)
            elif kind in (RecordKind.RESPONSE, RecordKind.EXCEPTION) and frame is not None:
                ri = record.request_index
                if ri is None or ri not in requests or waiting.get(ri) is not None:
                    continue  # unsolicited, or a second answer: not an exchange
                ts, stream, unit, pdu = requests.pop(ri)
                waiting[ri] = Exchange(ri, ts, stream, unit, pdu, frame.pdu)
            elif kind is RecordKind.EVENT and record.event is not None:
                ri = record.event.info.get("request_index")
                if isinstance(ri, int) and ri in requests:
                    ts, stream, unit, pdu = requests.pop(ri)
                    waiting[ri] = Exchange(ri, ts, stream, unit, pdu, None)
            while order and waiting.get(order[0]) is not None:
                done = waiting.pop(order.popleft())
                assert done is not None
                yield done
    for ri in order:  # the log ended first: what was answered, then the rest unanswered
        done = waiting.get(ri)
        if done is None:
            ts, stream, unit, pdu = requests[ri]
            done = Exchange(ri, ts, stream, unit, pdu, None)
        yield done
