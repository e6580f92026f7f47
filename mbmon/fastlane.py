"""The fused reader of ``mbmon read FILE --json``: the common case in one loop.

The general flow builds four objects per ADU (``Chunk``, ``Frame``,
``Transaction``, ``Record``) and crosses five stages to print one JSON line;
on a large capture that is most of the time spent. For the common case (a
capture file read to ``--json`` on stdout, no ``-w``, no ``--profile``) the
:class:`FastLane` takes the capture reader's place at the packet level and, for
a packet that is

* Ethernet / IPv4 without options / TCP, unfragmented, without SYN, FIN or RST,
* on a known Modbus/TCP connection that is open and carries MBAP
  (not RTU over TCP),
* exactly at the expected sequence number, with nothing held out of order,
  and with an acknowledgement that reveals no lost bytes,
* and whose stream direction's MBAP decoder is in sync (the start of a split
  ADU that it holds is joined to the payload, as the decoder would),

frames its ADUs, pairs them and makes their JSON lines in one loop, on the
*same* state objects the general flow uses: the TCP connection and its halves,
the MBAP decoder, the pairer's pending requests, the pipeline's record index
and counters, and the formatter's caches. Anything else (a handshake, a
retransmission, a gap, noise, a reused transaction id, a timeout, a cache
miss, another link type, UDP, RTU, IPv6, pcapng-only features) is handed to
the general code for that packet, ADU or record, and the loop goes on. The
output is therefore the general flow's, byte for byte, which
``tests/test_fastlane.py`` checks on every capture and on generated streams
full of the cases above. ``MBMON_NO_FASTLANE=1`` turns the lane off.

Owns no state of its own beyond its counters and the lines not yet written.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from mbmon.format import (
    _IDS_BYTES,
    _JSON_PARTS,
    _LATENCY_BYTES,
    _LINE_BYTES,
    _NO_REQUEST_BYTES,
    View,
    _json_bytes,
    _last_second,
    format_time,
    record_json_bytes,
)
from mbmon.model import (
    Direction,
    Frame,
    Kind,
    Record,
    Transport,
    fast_constructor,
)
from mbmon.pipeline import _KIND_OF_PDU, Pipeline
from mbmon.protocol.pairing import _needs_request
from mbmon.protocol.pdu import decode_pdu
from mbmon.sources.pcapfile import _Dissector, _eth_ipv4_tcp
from mbmon.sources.tcpflow import ACK, MAX_ACK_JUMP

__all__ = ["FastLane", "enabled"]

_BLOCK = 512  # lines per write
_CACHE_SIZE = 8192  # templates per direction, emptied when full

_new_frame = fast_constructor(Frame)
_new_record = fast_constructor(Record)
_C2S, _S2C = Direction.C2S, Direction.S2C
_TCP = Transport.TCP
_EXCEPTION = Kind.EXCEPTION


def _esc(text: bytes) -> bytes:
    """``text`` as literal text of a ``%``-format."""
    return text.replace(b"%", b"%%")


def enabled() -> bool:
    """Whether the fused reader may be used (``MBMON_NO_FASTLANE`` unset or empty)."""
    return not os.environ.get("MBMON_NO_FASTLANE")


class FastLane:
    """JSON lines of a capture's records, through the fused loop where it applies.

    ``pipeline`` must have no annotator (its notes would vary per record).
    ``write`` takes UTF-8 bytes (stdout's binary buffer). Use :meth:`bind` as
    the ``lane`` of :func:`~mbmon.sources.pcapfile.read_capture`; what the capture
    iterator still yields (releases at its end, a damage report) goes through the
    pipeline as usual, its records to :meth:`records`; :meth:`flush` writes.
    """

    def __init__(self, pipeline: Pipeline, view: View, write: Callable[[bytes], Any]) -> None:
        if pipeline.annotator is not None:
            raise ValueError("the fused reader works without an annotator only")
        self.pipeline = pipeline
        self.view = view
        self.write = write
        self.lines: list[bytes] = []
        self.fast_adus = 0  # ADUs framed, paired and printed by it
        self.general_packets = 0  # packets handed to the general dissector

    # ------------------------------------------------------------------ output

    def records(self, records: list[Record]) -> None:
        """JSON lines of records made by the general flow."""
        view = self.view
        self.lines.extend([record_json_bytes(record, view) for record in records])

    def flush(self, at_least: int) -> None:
        """Write the pending lines when there are at least ``at_least`` (0: always)."""
        lines = self.lines
        if lines and len(lines) >= at_least:
            lines.append(b"")
            self.write(b"\n".join(lines))
            lines.clear()

    # ------------------------------------------------------------------ the loop

    def template(self, record: Record) -> tuple[bytes, bytes | None]:
        """``record``'s JSON line, by the general encoder, and its template: ``None``
        unless the general encoder's parts for it are cached and the template gives
        the same line back.

        A template is the whole line as a ``%``-format of the values that differ
        between two records of the same stream direction, PDU, request PDU and
        unit: index, time (JSON and time of day), transaction id, latency and
        request index. It is checked against the general encoding of the record
        it was made from, so the line layout stays the formatter's.
        """
        line = record_json_bytes(record, self.view)
        frame = record.frame
        assert frame is not None
        stream, pdu, request = frame.stream, frame.pdu, record.request
        req_pdu = request.pdu if request is not None else None
        head = self.view._json_heads.get((stream.id, frame.direction))
        parts = _JSON_PARTS.get((id(pdu), id(req_pdu), record.kind, frame.unit, None))
        if (
            head is None
            or head[0] is not stream
            or parts is None
            or parts[0] is not pdu
            or parts[1] is not req_pdu
            or frame.tid is None
            or record.notes
        ):
            return line, None
        _, _, to_line, hex_text, note_json, note_escaped, to_latency, to_index, end = parts
        response = frame.direction is _S2C
        tail = _esc(note_escaped)
        if record.latency is not None:
            if record.request_index is None:
                return line, None
            tail += _LATENCY_BYTES  # its %.1f stays a format
            latency_json, request_index = b"%b", b"%d"
        else:
            latency_json = request_index = b"null"
            if response:
                tail += _esc(_NO_REQUEST_BYTES)
        before, between, after = _IDS_BYTES.split(b"%d")  # u%d t%d: unit fixed, tid a format
        ids = _esc(before) + b"%d" % frame.unit + _esc(between) + b"%d" + _esc(after)
        text = _LINE_BYTES % (b"%b%06d", b"%b", ids, _esc(hex_text), tail)
        tpl = b'{"index":%%d,"time":%%b%%b%%d%b"%b","notes":[%b]%b%b%b%b%b' % (
            _esc(to_line), text, _esc(note_json), _esc(to_latency),
            latency_json, _esc(to_index), request_index, _esc(end),
        )  # fmt: skip
        ts = record.ts
        whole = ts // 1
        usec = min((ts - whole) * 1e6 + 0.5, 999999)
        values: tuple[Any, ...] = (record.index, _json_bytes(ts), head[1], frame.tid,
                                   _last_second[2], usec, head[2], frame.tid)
        latency = record.latency
        if latency is not None:
            values += (latency * 1000, _json_bytes(round(latency * 1000, 3)), record.request_index)
        try:
            again = tpl % values
        except (TypeError, ValueError):
            return line, None
        return line, (tpl if again == line else None)

    def bind(self, dissector: _Dissector) -> Callable[..., None]:
        """The packet callback for ``dissector``'s capture: the fused loop."""
        pipeline = self.pipeline
        lines = self.lines
        append = lines.append
        records = self.records
        general_packet = dissector.packet
        tcp_flows = dissector.tcp
        decoders = pipeline._decoders
        make_decoder = pipeline._decoder
        pairer = pipeline.pairer
        pending = pairer._pending
        pending_index = pipeline._pending_index
        counts = pipeline.counts
        emit_decoded = pipeline._emit_decoded
        emit_transactions = pipeline._emit_transactions
        heads = self.view._json_heads
        tick_every = pipeline.config.tick_every
        template = self.template
        dumps = _json_bytes
        last_second = _last_second
        # id(TCP half) -> [MBAP decoder, JSON head or None]: a half lives as long as
        # the capture (the dissector keeps its connections), so its id is never reused
        halves: dict[int, list[Any]] = {}
        # (PDU bytes, unit) -> (Pdu, template) of requests
        requests: dict[tuple[bytes, int], tuple[Any, bytes]] = {}
        # (PDU bytes, unit, id(request Pdu)) -> (request Pdu, exception?, malformed?,
        # template) of responses
        responses: dict[tuple[bytes, int, int], tuple[Any, bool, bool, bytes]] = {}
        lane = self

        def general(
            ts: float, link: int, iface: int, buf: bytes, off: int, end: int, out: list[Any]
        ) -> None:
            """One packet through the general dissector and pipeline."""
            lane.general_packets += 1
            items: list[Any] = []
            general_packet(ts, link, iface, buf, off, end, items)
            for item in items:
                records(pipeline.feed(item))

        def packet(
            ts: float, link: int, iface: int, buf: bytes, off: int, end: int, out: list[Any]
        ) -> None:
            if link != 1 or end - off < 54:
                return general(ts, link, iface, buf, off, end, out)
            et, vihl, total, frag, proto, addrs, sport, dport, seq, ack, hl = _eth_ipv4_tcp(
                buf, off
            )
            if et != 0x0800 or vihl != 0x45 or proto != 6 or frag & 0x3FFF or hl & 0x07:
                return general(ts, link, iface, buf, off, end, out)
            flow = tcp_flows.get((addrs, sport, dport))
            ip_end = off + 14 + total
            doff = (hl >> 10) & 0x3C
            if flow is None or total < 40 or ip_end > end or not 20 <= doff <= total - 20:
                return general(ts, link, iface, buf, off, end, out)
            conn, from_client = flow
            stream = conn.stream
            if conn.closed or stream.transport is not _TCP:
                return general(ts, link, iface, buf, off, end, out)
            if from_client:
                half, other = conn._c2s, conn._s2c
            else:
                half, other = conn._s2c, conn._c2s
            if half.nxt != seq or half.held or half.fin is not None:
                return general(ts, link, iface, buf, off, end, out)
            if hl & ACK:  # an ack beyond what the other side delivered reveals a gap
                nxt = other.nxt
                if nxt is not None and nxt != ack and not other.done:
                    if 0 < (ack - nxt) & 0xFFFFFFFF <= MAX_ACK_JUMP:
                        return general(ts, link, iface, buf, off, end, out)
            payload = buf[off + 34 + doff : ip_end]
            size = len(payload)
            if not size:  # a pure ACK
                dissector.modbus_packets += 1
                return None
            state = halves.get(id(half))
            if state is None:
                direction = half.direction
                decoder = decoders.get((stream.id, direction))
                if decoder is None:
                    decoder = make_decoder(stream, direction)
                state = halves[id(half)] = [decoder, None]
            decoder, head = state
            if decoder._noise or not decoder._synced:
                return general(ts, link, iface, buf, off, end, out)
            dissector.modbus_packets += 1
            half.nxt = (seq + size) & 0xFFFFFFFF
            if decoder._buf:  # the rest of a split ADU: framed from the joined bytes
                payload = bytes(decoder._buf) + payload
                decoder._buf = bytearray()
            # ---- the pipeline's feed, for this chunk
            pipeline._last_ts = ts
            counts["chunks"] += 1
            counts["bytes"] += size
            size = len(payload)
            whole = ts // 1
            if whole != last_second[0]:
                format_time(ts)
            second = last_second[2]
            usec = min((ts - whole) * 1e6 + 0.5, 999999)
            ts_json = dumps(ts)
            sid = stream.id
            response = decoder._response
            max_len = decoder._max_length
            frames = malformed = exceptions = 0
            pos = 0
            while size - pos >= 6:
                length = (payload[pos + 4] << 8) | payload[pos + 5]
                if payload[pos + 2] or payload[pos + 3] or not 2 <= length <= max_len:
                    # noise: the general decoder takes the rest of this chunk
                    recs: list[Record] = []
                    emit_decoded(decoder.feed(payload[pos:], ts), recs)
                    records(recs)
                    pos = size
                    break
                stop = pos + 6 + length
                if stop > size:
                    break
                raw = payload[pos:stop]
                pos = stop
                unit = raw[6]
                tid = (raw[0] << 8) | raw[1]
                body = raw[7:]
                frames += 1
                pend = pending.get(sid)
                if not response:  # a request: remembered for its response
                    entry = requests.get((body, unit))
                    pdu = entry[0] if entry is not None else decode_pdu(body, False)
                    if pdu.malformed:
                        malformed += 1
                    frame = _new_frame(ts, stream, _C2S, unit, tid, pdu, raw, None)
                    if pend is None:
                        pend = pending[sid] = {}
                    elif (tid, unit) in pend or len(pend) >= pairer.max_pending:
                        recs = []  # a reused id or a full table: timeouts first
                        emit_transactions(pairer.feed(frame), recs)
                        records(recs)
                        continue
                    pend[(tid, unit)] = frame
                    index = pipeline._index
                    pipeline._index = index + 1
                    pending_index[id(frame)] = index
                    if entry is not None and head is not None:
                        append(entry[1] % (index, ts_json, head[1], tid, second, usec, head[2],
                                           tid))  # fmt: skip
                        continue
                    line, tpl = template(_new_record(
                        index, ts, _KIND_OF_PDU[pdu.kind], stream, frame, None, None, None,
                        None, None, None, (), None,
                    ))  # fmt: skip
                    append(line)
                    if tpl is not None:
                        if len(requests) >= _CACHE_SIZE:
                            requests.clear()
                        requests[(body, unit)] = (pdu, tpl)
                else:  # a response: paired by (tid, unit) when the function codes agree
                    req = pend.get((tid, unit)) if pend is not None else None
                    req_pdu = None
                    latency = request_index = None
                    if req is not None:
                        req_pdu = req.pdu
                        if req_pdu.fc == body[0] & 0x7F:
                            del pend[(tid, unit)]
                            if not pend:
                                del pending[sid]
                            latency = ts - req.ts
                            request_index = pending_index.pop(id(req), None)
                        else:
                            req = req_pdu = None
                    index = pipeline._index
                    pipeline._index = index + 1
                    entry = responses.get((body, unit, id(req_pdu)))
                    if (
                        entry is not None
                        and entry[0] is req_pdu
                        and head is not None
                        and (req is None or request_index is not None)
                    ):
                        if entry[1]:
                            exceptions += 1
                        if entry[2]:
                            malformed += 1
                        if req is None:
                            append(entry[3] % (index, ts_json, head[1], tid, second, usec,
                                               head[2], tid))  # fmt: skip
                        else:
                            append(entry[3] % (index, ts_json, head[1], tid, second, usec,
                                               head[2], tid, latency * 1000,  # type: ignore[operator]
                                               dumps(round(latency * 1000, 3)),  # type: ignore[operator]
                                               request_index))  # fmt: skip
                        continue
                    pdu = first = decode_pdu(body, True)
                    if req_pdu is not None and _needs_request(first, req_pdu):
                        pdu = decode_pdu(body, True, request=req_pdu)
                    is_exception = pdu.kind is _EXCEPTION
                    if is_exception:
                        exceptions += 1
                    if first.malformed:
                        malformed += 1
                    line, tpl = template(_new_record(
                        index, ts, _KIND_OF_PDU[pdu.kind], stream,
                        _new_frame(ts, stream, _S2C, unit, tid, pdu, raw, None),
                        req, request_index, latency, None, None, None, (), None,
                    ))  # fmt: skip
                    append(line)
                    if tpl is not None:
                        if len(responses) >= _CACHE_SIZE:
                            responses.clear()
                        responses[(body, unit, id(req_pdu))] = (
                            req_pdu, is_exception, first.malformed is not None, tpl
                        )
                if head is None:  # the general encoder made it with this record's line
                    head = heads.get((sid, half.direction))
                    if head is not None and head[0] is stream:
                        state[1] = head
                    else:
                        head = None
            if pos < size:
                decoder._buf = bytearray(payload[pos:])
            counts["frames"] += frames
            if malformed:
                counts["malformed"] += malformed
            if exceptions:
                counts["exceptions"] += exceptions
            lane.fast_adus += frames
            if ts >= pipeline._next_tick:
                pipeline._next_tick = ts + tick_every
                recs = []
                emit_transactions(pairer.tick(ts), recs)
                records(recs)
            if len(lines) >= _BLOCK:
                lines.append(b"")
                lane.write(b"\n".join(lines))
                lines.clear()
            return None

        return packet
