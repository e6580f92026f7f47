"""Wiring only: chunks and source events in, annotated records out.

One :class:`Pipeline` serves every source (pcap, live sniffing, serial,
proxy): each calls ``feed(chunk_or_event)`` and gets the records to hand to
the sinks. It keeps one sans-I/O decoder per (stream, direction) — one per bus
for RTU — one :class:`~mbmon.protocol.pairing.Pairer` for all streams, and the
annotator. Nothing here knows where bytes came from or where records go.

Which decoder frames a stream is the transport's business, and the transport's
only: :data:`DECODERS` maps each transport to a :class:`DecoderEntry` (how to
make the decoder of one stream direction, and whether each chunk is a whole
datagram that is flushed at once). A new transport registers its decoder with
:func:`register_decoder`; nothing here tests a transport by name.

Time reaches every stage through :meth:`Pipeline.tick`: decoders holding bytes
settle them after a silence, pairing times requests out, the annotator's
``tick`` (when it has one) reports commands, and streams idle for
``idle_timeout`` are flushed and forgotten. :meth:`Pipeline.next_deadline` is the
earliest time any of them needs a tick. Memory is bounded for runs of weeks: a
stream's state goes at its DISCONNECT (or when idle), pending requests are
bounded per stream and in total.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from mbmon import core
from mbmon.model import (
    Annotation,
    Chunk,
    CommandUpdate,
    Direction,
    Event,
    EventKind,
    Frame,
    Kind,
    Noise,
    Record,
    RecordKind,
    Stream,
    Transaction,
    Transport,
    TxStatus,
    fast_constructor,
)
from mbmon.protocol.mbap import MbapDecoder
from mbmon.protocol.pairing import DEFAULT_MAX_TOTAL, Pairer, expects_reply
from mbmon.protocol.rtu import RtuDecoder


class Annotator(Protocol):
    def annotate(self, tx: Transaction) -> Annotation: ...


class StreamDecoding(Protocol):
    """What the pipeline asks of a stream decoder (sans-I/O: see ``mbmon/protocol``)."""

    @property
    def buffered(self) -> int: ...

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]: ...

    def flush(self, ts: float) -> list[Frame | Noise]: ...

    def reset(self, ts: float) -> list[Noise]: ...

    def tick(self, now: float) -> list[Frame | Noise]: ...

    def next_deadline(self) -> float | None: ...


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Knobs of the analysis, not of any source."""

    timeout: float = 1.0  # seconds before an unanswered request is reported
    baudrate: int | None = None  # RTU bus speed, for silence hints and t3.5 ticks
    tick_every: float = 0.1  # how often (capture time) pending requests are checked
    silence: float | None = None  # quiet seconds before a decoder settles what it holds
    #                               (None: ``timeout``); see RtuDecoder/MbapDecoder.tick
    idle_timeout: float = 600.0  # seconds without input before tick forgets a stream
    max_pending: int = DEFAULT_MAX_TOTAL  # outstanding requests over all streams

    @property
    def settle_after(self) -> float:
        """Quiet seconds before a decoder settles what it holds (``silence``, else ``timeout``)."""
        return self.timeout if self.silence is None else self.silence


#: How to make the decoder of one direction of a stream (or of a bus).
DecoderFactory = Callable[[Stream, Direction, PipelineConfig], StreamDecoding]


@dataclass(frozen=True, slots=True)
class DecoderEntry:
    """A transport's stream decoder: ``make`` builds one per (stream, direction);
    ``datagram`` says each chunk is a whole datagram, flushed as soon as it is fed
    (nothing of it waits for the next one)."""

    make: DecoderFactory
    datagram: bool = False


#: The one registry of stream decoders, keyed by transport (a :class:`Transport`, or
#: any hashable a new source puts in ``Stream.transport``).
DECODERS: dict[Hashable, DecoderEntry] = {}


def register_decoder(transport: Hashable, make: DecoderFactory, *, datagram: bool = False) -> None:
    """Make ``make`` the decoder of every stream of ``transport`` (replacing any before).

    Takes effect for decoders made afterwards (a pipeline makes one when a
    stream direction first brings bytes)."""
    DECODERS[transport] = DecoderEntry(make, datagram)


def decoder_entry(transport: Hashable) -> DecoderEntry:
    """The registered decoder of ``transport``; ``ValueError`` when there is none."""
    try:
        return DECODERS[transport]
    except KeyError:
        raise ValueError(f"no stream decoder is registered for transport {transport!r}") from None


def _mbap(stream: Stream, direction: Direction, config: PipelineConfig) -> StreamDecoding:
    return MbapDecoder(stream, direction, silence=config.settle_after)


def _rtu(stream: Stream, direction: Direction, config: PipelineConfig) -> StreamDecoding:
    # the compiled framer when it covers the stream (no baud rate): the same frames
    framer: StreamDecoding | None = core.rtu_decoder(
        stream, direction, baudrate=config.baudrate, silence=config.settle_after
    )
    if framer is not None:
        return framer
    return RtuDecoder(stream, direction, baudrate=config.baudrate, silence=config.settle_after)


register_decoder(Transport.TCP, _mbap)
register_decoder(Transport.UDP, _mbap, datagram=True)
register_decoder(Transport.RTU, _rtu)
register_decoder(Transport.RTU_OVER_TCP, _rtu)
register_decoder(Transport.RTU_OVER_UDP, _rtu, datagram=True)


_KIND_OF_PDU = {
    Kind.REQUEST: RecordKind.REQUEST,
    Kind.RESPONSE: RecordKind.RESPONSE,
    Kind.EXCEPTION: RecordKind.EXCEPTION,
}

# Per ADU: enum members as module constants (an attribute of an enum class costs
# about 70 ns, a global 10 ns) and a Record constructor about twice as fast as the class.
_EXCEPTION = Kind.EXCEPTION
_PENDING, _TIMEOUT = TxStatus.PENDING, TxStatus.TIMEOUT
_UNSOLICITED = TxStatus.UNSOLICITED
#: the note of a proxy's own answer that came after its request was reported unanswered
LATE_NOTE = "late: its request was reported unanswered"
#: requests of joined streams reported unanswered, kept for a late answer (at most)
_LATE_KEPT = 1024
_S2C = Direction.S2C
_new_record = fast_constructor(Record)


class Pipeline:
    """Decoders, pairing and annotation for any number of streams."""

    def __init__(self, annotator: Annotator | None = None, config: PipelineConfig | None = None):
        self.config = config or PipelineConfig()
        self.annotator = annotator
        cfg = self.config
        self.pairer = Pairer(timeout=cfg.timeout, max_total=cfg.max_pending)
        self._decoders: dict[tuple[int, Direction], StreamDecoding] = {}
        # decoders that held bytes after a chunk: the only ones a tick may concern
        self._waiting: dict[tuple[int, Direction], StreamDecoding] = {}
        self._streams: dict[int, Stream] = {}  # streams with a decoder
        # decoders of datagram transports: each chunk is flushed as soon as it is fed
        self._datagram: set[tuple[int, Direction]] = set()
        # when each stream with a decoder last brought bytes (idle expiry)
        self._last_input: dict[int, float] = {}
        # id(request frame) -> record index, for requests the pairer holds: an entry
        # goes when its request is answered or times out (or is cut off by damage)
        self._pending_index: dict[int, int] = {}
        self._index = 0
        self._next_tick = float("-inf")
        self._next_sweep = float("-inf")
        self._last_ts = 0.0
        self._damage_ts = float("-inf")  # last source damage (ERROR without a stream)
        # streams whose answers pair with another stream's requests (named by that
        # stream's CONNECT, info ``answers_on``): the note their answers carry
        self._joined_notes: dict[int, tuple[str, ...]] = {}
        self._answers_on: dict[int, int] = {}  # stream id -> the stream joined to it
        # requests on a joined stream (the proxy's own answers) reported unanswered:
        # (stream id, tid, unit) -> (request, its record index), for an answer the
        # proxy held behind another and wrote after the pairing's timeout
        self._late: dict[tuple[int, int | None, int], tuple[Frame, int | None]] = {}
        # streams whose source names their decoder (use_decoder), and those whose
        # requests are never reported unanswered (a frame typed alone)
        self._own_decoders: dict[int, DecoderEntry] = {}
        self._never_unanswered: set[int] = set()
        self.counts: dict[str, int] = {
            "chunks": 0,
            "bytes": 0,
            "frames": 0,
            "noise": 0,
            "noise_bytes": 0,
            "events": 0,
            "exceptions": 0,
            "timeouts": 0,
            "malformed": 0,
        }

    def use_decoder(
        self, stream: Stream, entry: DecoderEntry, *, report_unanswered: bool = True
    ) -> None:
        """Frame ``stream`` with ``entry`` instead of its transport's decoder: a source
        that knows where its ADUs begin and end (``decode``'s typed bytes, one ADU
        per chunk) says so. ``report_unanswered=False``: a request of the stream left
        without its answer is no timeout (nothing after it was observed)."""
        self._own_decoders[stream.id] = entry
        if not report_unanswered:
            self._never_unanswered.add(stream.id)

    # ------------------------------------------------------------------ input

    def feed(self, item: Chunk | Event) -> list[Record]:
        """Take one chunk or source event; return the records it completes, in order."""
        out: list[Record] = []
        if isinstance(item, Chunk):
            ts = item.ts
            self._last_ts = ts
            counts = self.counts
            counts["chunks"] += 1
            counts["bytes"] += len(item.data)
            if ts >= self._next_tick:
                # requests whose answer was due before this chunk: reported first, at
                # their due time (as the live loop's tick would have), so records stay
                # in time order and an answer in this chunk after the timeout is late
                self._next_tick = ts + self.config.tick_every
                self._emit_transactions(self.pairer.tick(ts), out)
            stream = item.stream
            key = (stream.id, item.direction)
            decoder = self._decoders.get(key)
            if decoder is None:
                decoder = self._decoder(stream, item.direction)
            self._last_input[stream.id] = ts
            decoded = decoder.feed(item.data, ts)
            if decoded:
                self._emit_decoded(decoded, out)
            if key in self._datagram:
                self._emit_decoded(decoder.flush(ts), out)
            elif decoder.buffered:
                self._waiting[key] = decoder
            return out
        return self._feed_event(item, out)

    def _feed_event(self, item: Event, out: list[Record]) -> list[Record]:
        """A source event: damage, a gap (the decoder resets), a disconnect (the stream ends)."""
        self._last_ts = max(self._last_ts, item.ts)
        stream = item.stream
        if item.kind is EventKind.ERROR and stream is None:
            # requests still waiting may have had their answers in the damaged part:
            # those not yet expired are never reported as unanswered
            self._emit_transactions(self.pairer.tick(item.ts), out)
            self._damage_ts = max(self._damage_ts, item.ts)
        if item.kind is EventKind.GAP and stream is not None:
            direction = Direction(item.info.get("direction", Direction.C2S.value))
            decoder = self._decoders.get((stream.id, direction))
            if decoder is not None:
                self._emit_decoded(decoder.reset(item.ts), out)
        if item.kind is EventKind.CONNECT and stream is not None:
            self._join(stream, item.info)
        out.append(self._event_record(item))
        if item.kind is EventKind.DISCONNECT and stream is not None:
            self._close_stream(stream, item.ts, out)
            if self._answers_on:
                self._part(stream, item.ts, out)
        return out

    def _join(self, stream: Stream, info: Mapping[str, Any]) -> None:
        """A stream whose requests may be answered on another (``answers_on``: its id;
        a proxy's own answers to a client), and the note those answers carry."""
        other = info.get("answers_on")
        if type(other) is int and other != stream.id:
            self.pairer.join(other, stream.id)
            self._answers_on[stream.id] = other
            note = info.get("note")
            self._joined_notes[other] = (note,) if isinstance(note, str) and note else ()

    def _part(self, stream: Stream, ts: float, out: list[Record]) -> None:
        """``stream`` ended: so does the stream its requests were answered on."""
        other = self._answers_on.pop(stream.id, None)
        if other is None:
            return
        self.pairer.part(other)
        self._joined_notes.pop(other, None)
        if self._late:
            for key in [k for k in self._late if k[0] == other]:
                del self._late[key]
        joined = self._streams.get(other)
        if joined is not None:
            self._close_stream(joined, ts, out)

    def tick(self, now: float) -> list[Record]:
        """Time is ``now``: every stage reports what time alone completes.

        Decoders settle bytes held after a silence (frames and noise stamped when
        their bytes arrived), requests older than the timeout are reported
        unanswered, the annotator's ``tick`` (when it has one) reports command
        updates, and streams idle for ``idle_timeout`` are flushed and forgotten.
        """
        out: list[Record] = []
        waiting = self._waiting
        if waiting:
            for key, decoder in list(waiting.items()):
                deadline = decoder.next_deadline()
                if deadline is not None and deadline <= now:
                    decoded = decoder.tick(now)
                    if decoded:
                        self._emit_decoded(decoded, out)
                    deadline = decoder.next_deadline()
                if deadline is None and not decoder.buffered:
                    del waiting[key]
        self._emit_transactions(self.pairer.tick(now), out)
        annotator_tick = getattr(self.annotator, "tick", None)
        if annotator_tick is not None:
            for cmd in annotator_tick(now) or ():
                out.append(self._record(cmd.ts, RecordKind.COMMAND, cmd.stream, command=cmd))
        if now >= self._next_sweep:
            idle = self.config.idle_timeout
            self._next_sweep = now + min(max(idle / 10, 0.01), 60.0)
            self._expire_idle(now - idle, out)
        return out

    def next_deadline(self) -> float | None:
        """The earliest time a :meth:`tick` would report something, or ``None``:
        the minimum over the decoders holding bytes, the pairer and the annotator."""
        deadlines = [self.pairer.next_deadline()]
        for key, decoder in list(self._waiting.items()):
            deadline = decoder.next_deadline()
            if deadline is None and not decoder.buffered:
                del self._waiting[key]
            deadlines.append(deadline)
        annotator_deadline = getattr(self.annotator, "next_deadline", None)
        if annotator_deadline is not None:
            deadlines.append(annotator_deadline())
        known = [d for d in deadlines if d is not None]
        return min(known) if known else None

    def finish(self, ts: float | None = None) -> list[Record]:
        """End of input: flush every decoder and report every request still unanswered.

        The pipeline is then as new but for its record numbers (and the annotator's
        state): more input (another source's, read after this one) is decoded with
        its own time, untouched by this input's clock, damage or joined streams."""
        when = self._last_ts if ts is None else ts
        out: list[Record] = []
        for key in list(self._decoders):
            self._emit_decoded(self._decoders.pop(key).flush(when), out)
        self._waiting.clear()
        self._streams.clear()
        self._datagram.clear()
        self._last_input.clear()
        self._emit_transactions(self.pairer.flush(when), out)
        for other in self._answers_on.values():
            self.pairer.part(other)
        self._answers_on.clear()
        self._joined_notes.clear()
        self._late.clear()
        self._next_tick = self._next_sweep = self._damage_ts = float("-inf")
        self._last_ts = 0.0
        return out

    def run(self, items: Iterable[Chunk | Event]) -> Iterable[Record]:
        """Convenience for offline input: every record of ``items``, then of ``finish()``."""
        for item in items:
            yield from self.feed(item)
        yield from self.finish()

    # ------------------------------------------------------------------ internals

    def _decoder(self, stream: Stream, direction: Direction) -> StreamDecoding:
        key = (stream.id, direction)
        decoder = self._decoders.get(key)
        if decoder is None:
            entry = self._own_decoders.get(stream.id) or decoder_entry(stream.transport)
            self._streams[stream.id] = stream
            decoder = entry.make(stream, direction, self.config)
            self._decoders[key] = decoder
            if entry.datagram:
                self._datagram.add(key)
        return decoder

    def _close_stream(self, stream: Stream, ts: float, out: list[Record]) -> None:
        """Flush the stream's decoders and forget them (a DISCONNECT, or idle)."""
        sid = stream.id
        for direction in (Direction.C2S, Direction.S2C, Direction.BUS):
            decoder = self._decoders.pop((sid, direction), None)
            if decoder is not None:
                self._waiting.pop((sid, direction), None)
                self._datagram.discard((sid, direction))
                self._emit_decoded(decoder.flush(ts), out)
        self._streams.pop(sid, None)
        self._last_input.pop(sid, None)

    def _expire_idle(self, before: float, out: list[Record]) -> None:
        """Streams with no input since ``before``: flushed (nothing is lost) and forgotten."""
        for sid, last in list(self._last_input.items()):
            if last < before:
                stream = self._streams.get(sid)
                if stream is not None:
                    self._close_stream(stream, last, out)

    def _next_index(self) -> int:
        index = self._index
        self._index += 1
        return index

    def _emit_decoded(self, items: Sequence[Frame | Noise], out: list[Record]) -> None:
        counts = self.counts
        pair = self.pairer.feed
        for item in items:
            if isinstance(item, Frame):
                counts["frames"] += 1
                if item.pdu.malformed:
                    counts["malformed"] += 1
                self._emit_transactions(pair(item), out)
            else:
                counts["noise"] += 1
                counts["noise_bytes"] += len(item.raw)
                out.append(self._record(item.ts, RecordKind.NOISE, item.stream, noise=item))

    def _emit_transactions(self, txs: list[Transaction], out: list[Record]) -> None:
        annotator = self.annotator
        pending_index = self._pending_index
        for tx in txs:
            status = tx.status
            if status is _TIMEOUT:
                request = tx.request
                assert request is not None
                req_index = pending_index.pop(id(request), None)
                if request.ts <= self._damage_ts < request.ts + self.pairer.timeout:
                    continue  # its answer may have been lost to damage: not made up
                if request.stream.id in self._never_unanswered:
                    continue
                self.counts["timeouts"] += 1
                info = {"request_index": req_index, "unit": request.unit, "fc": request.pdu.fc}
                if request.tid is not None:
                    info["tid"] = request.tid
                event = Event(tx.ts, request.stream, EventKind.TIMEOUT, info)
                out.append(self._event_record(event))
                if request.stream.id in self._joined_notes:
                    self._keep_late(request, req_index)
                continue
            late: tuple[Transaction, int | None] | None = None
            if status is _UNSOLICITED and self._late:
                late = self._late_answer(tx)
                if late is not None:
                    tx = late[0]
                    status = tx.status
            response = tx.response
            request = tx.request
            frame = response if response is not None else request  # tx.frame
            assert frame is not None
            annotation = annotator.annotate(tx) if annotator is not None else None
            index = self._index
            self._index = index + 1
            request_index = None
            if status is _PENDING:
                # what the pairer holds: not an RTU broadcast, not Diagnostics 04
                if (frame.tid is not None or frame.unit) and (
                    frame.pdu.fc != 0x08 or expects_reply(frame)
                ):
                    pending_index[id(frame)] = index
            elif request is not None:
                request_index = pending_index.pop(id(request), None)
            kind = frame.pdu.kind
            if kind is _EXCEPTION:
                self.counts["exceptions"] += 1
            notes = annotation.notes if annotation is not None else ()
            if self._joined_notes and frame.direction is _S2C:
                notes = notes + self._joined_notes.get(frame.stream.id, ())
            if late is not None:
                request_index = late[1]
                notes = (*notes, LATE_NOTE)
            out.append(
                _new_record(
                    index,
                    frame.ts,
                    _KIND_OF_PDU[kind],
                    frame.stream,
                    frame,
                    request if response is not None else None,
                    request_index,
                    tx.latency,
                    None,  # noise
                    None,  # event
                    None,  # command
                    notes,
                    annotation.state if annotation is not None else None,
                )
            )
            if annotation is not None and annotation.commands:
                for cmd in annotation.commands:
                    out.append(self._record(cmd.ts, RecordKind.COMMAND, cmd.stream, command=cmd))

    def _keep_late(self, request: Frame, index: int | None) -> None:
        """A request the proxy answers itself (on a joined stream) was reported
        unanswered: kept (a bounded number), so that its answer, held behind another
        answer half-way to the client and written late, pairs with it."""
        late = self._late
        if len(late) >= _LATE_KEPT:
            del late[next(iter(late))]
        late[(request.stream.id, request.tid, request.unit)] = (request, index)

    def _late_answer(self, tx: Transaction) -> tuple[Transaction, int | None] | None:
        """An answer nothing waited for, on a joined stream: the proxy's own answer to
        a request reported unanswered (:meth:`_keep_late`), as that request's answer
        (its latency the real one) and the request's record index; else ``None``."""
        response = tx.response
        if response is None:
            return None
        kept = self._late.pop((response.stream.id, response.tid, response.unit), None)
        if kept is None:
            return None
        request, index = kept
        status = TxStatus.EXCEPTION if response.pdu.kind is _EXCEPTION else TxStatus.ANSWERED
        return Transaction(tx.ts, status, request, response, response.ts - request.ts), index

    def _event_record(self, event: Event) -> Record:
        self.counts["events"] += 1
        return self._record(event.ts, RecordKind.EVENT, event.stream, event=event)

    def _record(
        self,
        ts: float,
        kind: RecordKind,
        stream: Stream | None,
        *,
        noise: Noise | None = None,
        event: Event | None = None,
        command: CommandUpdate | None = None,
    ) -> Record:
        """A record for something other than a frame (noise, event, command)."""
        return _new_record(
            self._next_index(), ts, kind, stream, None, None, None, None, noise, event, command,
            (), None,
        )  # fmt: skip
