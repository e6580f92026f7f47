# RTU pairing and lines in the compiled core (included by _reader.pyx).
#
# ``_RtuPass`` runs ``mbmon read --rtu-raw FILE`` end to end: the bus's bytes in the
# reference's reads (RawRtuSource's chunk size, time 0.0) -> the compiled framer
# (mbmon.core._rtu.RtuCore, its packed output: no Python object per frame) -> the
# RTU pairing rules of mbmon.protocol.pairing (one pending request per bus, unit and
# function code must agree, a new request times the pending one out, broadcasts and
# Diagnostics 04 never pending, unsolicited answers) -> the text or JSON line, in the
# order and with the record numbers of mbmon.pipeline. It also reads a capture of
# RTU buses (link type 147, USER0: ``run_bus``), each record a chunk of its bus at
# the record's time, one framer and one pending request per bus (``switch_bus``).
#
# It is a _Pass: the line pieces (put_note, put_values_json, native_pdu, the time,
# the JSON answer's tail, the output buffer, events and the reference records)
# are the TCP side's own; only what differs for RTU is here: the line's head (no
# transaction id, "#N" for an untimed bus), the JSON head ("transport":"rtu",
# "tid":null, "crc_ok":true), the one pending slot, the reference objects of an
# RTU frame (the PDU between the unit and the CRC) and the noise runs (formatted
# by mbmon.format, as they come rarely).

DEF MAX_BUSES = 64          # RTU buses of one capture the core keeps (USER0 interfaces)


cdef struct _RRec:          # one packed record of RtuCore.take() (``<BBHId``)
    uint8_t kind            # 0 request, 1 response, 2 noise run
    uint8_t pad
    unsigned short length   # frame bytes
    uint32_t offset         # frame: offset in the raw bytes; noise: index in the list
    double ts


cdef class _RtuPass(_Pass):
    """One RTU bus stream read to lines (see the comment at the top of _rtu_pass.pxi)."""

    cdef object framer          # the compiled RtuCore of the bus
    cdef object rstream         # the bus's Stream
    cdef bint timed             # the stream has capture times (else "#N", no latency)
    cdef bint has_pend          # the pairer holds a request (pend)
    cdef Pend pend
    cdef public int64_t noise_records, noise_bytes, crc_errors
    # a Read/Write Multiple Registers (0x17) request written here: its write part
    cdef bint rw
    cdef int rw_address, rw_count, rw_bytes
    cdef const uint8_t* rw_values
    cdef int rw_max_read, rw_max_write
    # a capture of buses (USER0): one framer, stream and pending slot per bus; the
    # fields above are the current bus's (switch_bus saves and loads them)
    cdef int cur                # the current bus
    cdef list framers           # bus -> its RtuCore
    cdef list bstreams          # bus -> its Stream
    cdef dict bus_by_iface      # interface -> bus
    cdef Pend* bpend            # bus -> its pending request (saved)
    cdef uint8_t bhas[MAX_BUSES]  # bus -> whether it has one (saved)
    cdef bint multi             # more than one bus (pend_order is kept from then on)
    cdef list pend_order        # buses with a pending request, in the pairer's order
    cdef list fed_order         # buses in the order of their first bytes (decoders made)

    def __init__(self, bint emit, bint as_json, double timeout, view, write, stream):
        from mbmon.core._rtu import PACKED, RtuCore

        if PACKED.size != sizeof(_RRec):
            raise ImportError("mbmon.core._rtu packs its records other than the reader reads them")
        _Pass.__init__(self, emit, as_json, timeout, frozenset(), view, write)
        self.rstream = stream
        self.timed = stream.timed
        # the pipeline's RTU decoder: no baud rate, silence = its settle time (timeout)
        self.framer = RtuCore(stream, Direction.BUS, None, timeout)
        self.streams = [None] * stream.id + [stream]
        self.labels = [None] * (stream.id + 1)
        self.heads = [None] * (stream.id + 1)
        self.has_pend = False
        self.cur = 0
        self.framers = [self.framer]
        self.bstreams = [stream]
        self.bus_by_iface = {}
        self.multi = False
        self.pend_order = []
        self.fed_order = []
        self.bpend = <Pend*>malloc(sizeof(Pend) * MAX_BUSES)
        if self.bpend == NULL:
            raise MemoryError()
        memset(self.bhas, 0, MAX_BUSES)
        self.noise_records = self.noise_bytes = self.crc_errors = 0
        from mbmon.protocol.functions import FUNCTIONS

        rw = FUNCTIONS.get(0x17)
        # the spec's limits of the row (0: no such row, the reference formats 0x17)
        self.rw_max_read = (rw.max_count or 0) if rw is not None and rw.shape == "read_write" else 0
        self.rw_max_write = (rw.max_write_count or 0) if self.rw_max_read else 0

    def __dealloc__(self):
        free(self.bpend)

    def select(self, flt, count, bint show):
        """``_Pass.select``; on a bus without capture times the filters ignore
        ``--since``/``--until`` (``RecordFilter.matches_record``: every record of a raw
        dump is at time 0.0), so the native frames' test (``fast_pass``) does too."""
        _Pass.select(self, flt, count, show)
        if not self.timed:
            self.f_since = self.f_until = False

    def run_rtu(self, data, Py_ssize_t read_size) -> None:
        """The dump ``data`` (bytes or a buffer) in reads of ``read_size`` bytes, as the
        reference's source reads it (``RawRtuSource.chunk_size``), then its end."""
        cdef Py_ssize_t n = len(data), pos = 0, end
        if read_size < 1:
            raise ValueError("read_size must be at least 1")
        view = memoryview(data)
        try:
            while pos < n:
                end = pos + read_size if n - pos > read_size else n
                self.rtu_chunk(bytes(view[pos:end]), 0.0)
                pos = end
        finally:
            view.release()
        self.rtu_finish(self.pl_last)
        self.flush_out()

    def run_bus(self, const uint8_t[::1] data) -> None:
        """A capture of RTU buses (pcap or pcapng, link type 147: USER0): every
        record's bytes a chunk of the bus at the record's time, as the reference's
        dissector makes them (``Dissector._bus``), then the end of input. Declines
        (``Declined``) a damaged container, another link type, more than MAX_BUSES buses."""
        self.run(data)  # the capture pass's container reading; records reach packet()
        self.rtu_finish(self.pl_last)
        self.flush_out()

    cdef int packet(self, double ts, int link, const uint8_t[::1] buf, Py_ssize_t off,
                    Py_ssize_t end) except -1:
        """One record of a capture of a bus (``run_bus``): link type 147, its bytes a
        chunk of the bus (an empty one makes none); a record of an interface never
        described is skipped, as the reference skips it."""
        if link != 147:
            if link < 0:
                return 0
            raise Declined("link type %d beside an RTU bus (USER0)" % link)
        cdef object b = self.bus_by_iface.get(self.rec_iface)
        if b is None:
            b = self.new_bus(self.rec_iface)
        if <int>b != self.cur:
            self.switch_bus(<int>b)
        if end > off:
            self.rtu_chunk(PyBytes_FromStringAndSize(<const char*>&buf[off], end - off), ts)
        return 0

    cdef int new_bus(self, int iface) except -1:
        """The bus of a new interface (``Dissector._bus``): the first is the stream made
        with the pass, the next ones ``NAME#IFACE`` on the next stream ids."""
        cdef int b = len(self.bus_by_iface)
        if b >= MAX_BUSES:
            raise Declined("more RTU buses than the core keeps")
        if b == 1:  # from now on the pairer's order of the buses' requests is kept
            self.multi = True
            self.pend_order = [0] if self.has_pend else []
        if b:
            name = self.bstreams[0].server + "#%d" % iface
            stream = Stream(self.bstreams[0].id + b, Transport.RTU, name, name,
                            timed=self.timed)
            self.bstreams.append(stream)
            self.framers.append(type(self.framer)(stream, Direction.BUS, None, self.timeout))
            self.streams.append(stream)
            self.labels.append(None)
            self.heads.append(None)
        self.bus_by_iface[iface] = b
        return b

    cdef int switch_bus(self, int b) except -1:
        """Make bus ``b`` the current one: its framer, stream and pending request."""
        self.bhas[self.cur] = self.has_pend
        memcpy(&self.bpend[self.cur], &self.pend, sizeof(Pend))
        self.cur = b
        self.framer = self.framers[b]
        self.rstream = self.bstreams[b]
        self.has_pend = self.bhas[b]
        memcpy(&self.pend, &self.bpend[b], sizeof(Pend))
        return 0

    cdef int rtu_chunk(self, bytes data, double ts) except -1:
        """One chunk of the bus (``Pipeline.feed``): the pairer's tick before it, then
        what the framer completes."""
        cdef int here = self.cur, b
        self.last_ts = ts
        self.pl_last = ts
        if ts >= self.next_tick:
            self.next_tick = ts + TICK_EVERY
            if not self.multi:
                if self.has_pend and self.pend.ts <= ts - self.timeout:
                    self.rtu_timeout(min(self.pend.ts + self.timeout, ts))
            else:  # every bus's pending request, in the pairer's order (Pairer.tick)
                for b in list(self.pend_order):
                    self.switch_bus(b)
                    if self.pend.ts <= ts - self.timeout:
                        self.rtu_timeout(min(self.pend.ts + self.timeout, ts))
                        self.pend_order.remove(b)
                if self.cur != here:
                    self.switch_bus(here)
        if self.multi and here not in self.fed_order:
            self.fed_order.append(here)
        elif not self.fed_order:
            self.fed_order.append(here)
        self.framer.push(data, ts)
        return self.rtu_drain()

    cdef int rtu_finish(self, double ts) except -1:
        """The end of input (``Pipeline.finish``): the framer flushes, then the pending
        request times out."""
        cdef int b
        if not self.multi:
            self.framer.push_flush(ts)
            self.rtu_drain()
            if self.has_pend:
                self.rtu_timeout(min(self.pend.ts + self.timeout, ts))
            return 0
        for b in self.fed_order:  # the decoders flush in the order they were made
            self.switch_bus(b)
            self.framer.push_flush(ts)
            self.rtu_drain()
        for b in self.pend_order:  # then the pairer's pending requests time out
            self.switch_bus(b)
            self.rtu_timeout(min(self.pend.ts + self.timeout, ts))
        self.pend_order = []
        return 0

    cdef int rtu_drain(self) except -1:
        """Every frame and noise run the framer made since the last call, in order."""
        cdef bytes recs, raw
        cdef list noises
        cdef _RRec r
        cdef Py_ssize_t i, count, nraw
        cdef const uint8_t* rp
        cdef const uint8_t* bp
        recs, raw, noises = self.framer.take()
        count = len(recs) // sizeof(_RRec)
        if not count:
            return 0
        rp = <const uint8_t*><char*>recs
        bp = <const uint8_t*><char*>raw
        nraw = len(raw)
        for i in range(count):
            memcpy(&r, rp + i * sizeof(_RRec), sizeof(_RRec))
            if r.kind == 2:
                self.rtu_noise(noises[r.offset])
                continue
            # the framer's bounds (4..257 bytes, inside its raw bytes) checked here too: a
            # request is copied into the pending slot (Pend.raw, 262 bytes)
            if r.length < 4 or r.length > 262 or <Py_ssize_t>r.offset + r.length > nraw:
                raise RuntimeError("the RTU framer's packed record points outside its frames")
            self.rtu_frame(r.kind, r.ts, bp + r.offset, r.length)
        return 0

    # ------------------------------------------------------------------ pairing

    cdef int rtu_frame(self, int d, double ts, const uint8_t* adu, int alen) except -1:
        """One frame through the RTU pairing rules (``Pairer._request``/``_response``)."""
        cdef int unit = adu[0]
        cdef bint hold
        self.frames += 1
        cdef bint was = self.has_pend
        if d == 0:
            if was:  # one request at a time on a bus: the pending one times out
                self.rtu_timeout(min(self.pend.ts + self.timeout, ts))
            hold = unit != 0 and (adu[1] != 0x08 or _expects_reply_rtu(adu, alen))
            if self.multi and was and not hold:
                self.pend_order.remove(self.cur)  # the pairer drops the bus's entry
            if hold:
                if self.multi and not was:
                    self.pend_order.append(self.cur)  # else the bus keeps its place
                self.has_pend = True
                self.pend.ts = ts
                self.pend.index = self.index
                self.pend.sid = self.rstream.id
                self.pend.tid = -1
                self.pend.unit = unit
                self.pend.fc = adu[1]
                self.pend.alen = alen
                memcpy(self.pend.raw, adu, alen)
            return self.rtu_record(0, ts, adu, alen, NULL)
        if self.has_pend and self.pend.unit == unit and self.pend.fc == adu[1] & 0x7F:
            self.has_pend = False
            if self.multi:
                self.pend_order.remove(self.cur)
            return self.rtu_record(1, ts, adu, alen, &self.pend)
        return self.rtu_record(1, ts, adu, alen, NULL)

    cdef int rtu_timeout(self, double ts) except -1:
        """The pending request times out at ``ts`` (its TIMEOUT event, as the pipeline's)."""
        self.has_pend = False
        info = {"request_index": self.pend.index, "unit": self.pend.unit, "fc": self.pend.fc}
        return self.event(ts, self.rstream.id, EventKind.TIMEOUT, info)

    cdef int rtu_noise(self, object noise) except -1:
        """A noise run: counted as the summary counts it, formatted by mbmon.format."""
        cdef int64_t index = self.index
        self.noise_records += 1
        self.noise_bytes += len(noise.raw)
        if "CRC" in noise.reason:
            self.crc_errors += 1
        self.count_record(noise.ts, self.rstream.id, False)
        if not self.emit:
            return 0
        return self.put_record(Record(index, noise.ts, RecordKind.NOISE, noise.stream, noise=noise))

    # ------------------------------------------------------------------ lines

    cdef int rtu_record(self, int d, double ts, const uint8_t* adu, int alen, Pend* req) except -1:
        """The record of one RTU frame (``frame_record``'s RTU twin): a request, or a
        response with its request (``req``) or without (NULL)."""
        cdef int64_t index = self.index
        cdef int sid = self.rstream.id
        cdef Native nat, rnat
        cdef bint native
        cdef double latency = 0.0
        cdef const uint8_t* pdu = adu + 1
        cdef int plen = alen - 3
        if d == 0:
            self.requests += 1
        elif adu[1] & 0x80:
            self.exceptions += 1
        else:
            self.responses += 1
        if d == 1 and req == NULL:
            self.unsolicited += 1
        self.count_record(ts, sid, True)
        if req != NULL:
            latency = ts - req.ts
        if not self.emit:
            if not self.rtu_native(d, pdu, plen, req, &nat, &rnat):
                self.rtu_objects(d, ts, adu, alen, req)  # counts a malformed PDU
            return 0
        native = self.rtu_native(d, pdu, plen, req, &nat, &rnat)
        if not native or self.f_slow:  # --where: its test reads the reference's Record
            return self.rtu_python(index, d, ts, adu, alen, req, latency)
        if req != NULL and nat.kind != 0 and not nat.has_addr and rnat.has_addr:
            nat.has_addr = 1
            nat.address = rnat.address
            nat.count = rnat.count
        if self.f_on and not self.f_grep and not self.fast_pass(ts, adu[0], &nat):
            return 0  # not shown, not counted by -c (the filters' test, _Pass.fast_pass)
        stream = self.rstream
        if self.labels[sid] is None:
            self.labels[sid] = (
                self.view.label(stream, Direction.C2S).encode("utf-8"),
                self.view.label(stream, Direction.S2C).encode("utf-8"),
            )
            self.heads[sid] = (
                _inner(_orjson.dumps({"stream": sid, "src": stream.client, "dst": stream.server})),
                _inner(_orjson.dumps({"stream": sid, "src": stream.server, "dst": stream.client})),
            )
        cdef Buf* o = &self.out
        cdef Py_ssize_t note_at, note_end, line_at, line_end
        cdef Py_ssize_t rec_at = o.n
        cdef bint js = self.as_json
        if js:
            put(o, b'{"index":', 9)
            put_i(o, index)
            put(o, b',"time":', 8)
            if self.timed:
                put_json_time(o, ts)
            else:
                put(o, b"null", 4)
            put_c(o, 44)
            put_bytes(o, self.heads[sid][d])
            put(o, b',"transport":"rtu","tid":null,"unit":', 37)
            put_u(o, adu[0])
            put(o, b',"fc":', 6)
            put_u(o, nat.fc)
            if nat.kind == 0:
                put(o, b',"kind":"request","exception_code":', 35)
            elif nat.kind == 1:
                put(o, b',"kind":"response","exception_code":', 36)
            else:
                put(o, b',"kind":"exception","exception_code":', 37)
            if nat.exc >= 0:
                put_u(o, nat.exc)
            else:
                put(o, b"null", 4)
            put(o, b',"address":', 11)
            if nat.has_addr:
                put_u(o, nat.address)
            else:
                put(o, b"null", 4)
            put(o, b',"count":', 9)
            if nat.has_addr and nat.count >= 0:
                put_u(o, nat.count)
            else:
                put(o, b"null", 4)
            put(o, b',"values":', 10)
            put_values_json(o, &nat)
            put(o, b',"pdu":"', 8)
            put_hex(o, pdu, plen)
            put(o, b'","line":"', 10)
        # the line: time (or "#N" on an untimed bus), label, [uUNIT], PDU hex, notes
        line_at = o.n
        if self.timed:
            self.put_time(ts)
        else:
            put_c(o, 35)
            put_i(o, index)
        put(o, b"  ", 2)
        put_bytes(o, self.labels[sid][d])
        put(o, b"  [u", 4)
        put_u(o, adu[0])
        put(o, b"]  ", 3)
        put_hex(o, pdu, plen)
        put(o, b"  | ", 4)
        note_at = o.n
        self.put_note(&nat)
        if self.rw:
            self.put_rw_note(o)
        note_end = o.n
        if req != NULL:
            if self.timed:
                put(o, b" (", 2)
                put_double(o, latency * 1000, b'f', 1, 0)
                put(o, b" ms)", 4)
        elif d == 1:
            put(o, b" (no matching request)", 22)
        line_end = o.n
        if js:
            put(o, b'","notes":["', 12)
            buf_need(o, note_end - note_at)
            memcpy(o.p + o.n, o.p + note_at, note_end - note_at)
            o.n += note_end - note_at
            put(o, b'"],"crc_ok":true,"latency_ms":', 30)
            if self.timed:
                self.put_json_answer_tail(o, req, latency)
            else:  # no capture times: no latency, but the request's index
                put(o, b'null,"malformed":null,"request_index":', 38)
                if req != NULL:
                    put_i(o, req.index)
                else:
                    put(o, b"null", 4)
                put_c(o, 125)
            if self.rw:  # the request's write part: the JSON's "fields", as the last key
                o.n -= 1
                self.put_rw_fields(o)
                put_c(o, 125)
        put_c(o, 10)
        if self.f_on or self.left >= 0:  # --grep's test on the line, -c's count
            return self.selected(rec_at, line_at, line_end, ts, adu[0], &nat, False)
        if o.n >= FLUSH_AT:
            self.flush_out()
        return 0

    cdef bint rtu_native(self, int d, const uint8_t* pdu, int plen, Pend* req, Native* nat,
                         Native* rnat) except -1:
        """Whether the core writes this frame's line itself (``frame_record``'s test)."""
        cdef bint native
        self.rw = False
        if plen >= 1 and pdu[0] == 0x17 and self.rw_max_read:
            native = self.rw_native(d, pdu, plen, req, nat)
        elif d == 0:
            native = native_pdu(pdu, plen, False, NULL, nat)
        elif req != NULL:
            native = (native_pdu(req.raw + 1, req.alen - 3, False, NULL, rnat)
                      and native_pdu(pdu, plen, True, rnat, nat))
        else:
            native = native_pdu(pdu, plen, True, NULL, nat)
        if native and self.fnames[nat.fc] is None:
            native = False
        if native and nat.exc >= 0 and self.enames[nat.exc] is None:
            native = False
        return native

    cdef bint rw_native(self, int d, const uint8_t* pdu, int plen, Pend* req, Native* nat) except -1:
        """A well-formed Read/Write Multiple Registers (0x17) request, or its answer (the
        read part's words: a register read's answer, its address and count the
        request's), as ``native_pdu`` decodes the codes it knows; False for the rest
        (malformed, a byte count its request breaks), which the reference formats."""
        cdef int address, count, waddr, wcount, wbc, bc
        cdef const uint8_t* rp
        nat.fc = 0x17
        nat.has_addr = 0
        nat.address = 0
        nat.count = -1
        nat.nvalues = -1
        nat.bits = 0
        nat.vdata = NULL
        nat.exc = -1
        nat.onoff = 0
        if d == 0:
            if plen < 10:
                return False
            address = be16(pdu + 1)
            count = be16(pdu + 3)
            waddr = be16(pdu + 5)
            wcount = be16(pdu + 7)
            wbc = pdu[9]
            if plen - 10 != wbc or wbc != 2 * wcount:
                return False
            if not 1 <= count <= self.rw_max_read or not 1 <= wcount <= self.rw_max_write:
                return False
            if address + count > 0x10000 or waddr + wcount > 0x10000:
                return False
            nat.kind = 0
            nat.has_addr = 1
            nat.address = address
            nat.count = count
            self.rw = True
            self.rw_address = waddr
            self.rw_count = wcount
            self.rw_bytes = wbc
            self.rw_values = pdu + 10
            return True
        if plen < 3:
            return False
        bc = pdu[1]
        if plen != bc + 2 or bc & 1 or bc == 0:
            return False
        nat.kind = 1
        nat.nvalues = bc >> 1
        nat.vdata = pdu + 2
        if req != NULL:
            if req.alen - 3 < 5:
                return False
            rp = req.raw + 1
            if bc != 2 * be16(rp + 3):
                return False  # decoded again with the request: malformed
            nat.has_addr = 1
            nat.address = be16(rp + 1)
            nat.count = be16(rp + 3)
        return True

    cdef int put_rw_note(self, Buf* o) except -1:
        """The end of a 0x17 request's note: ``, write A..B = v, v, ...`` (the generic
        note's, ``format.values_text`` for the words)."""
        cdef int i, shown
        put(o, b", write ", 8)
        put_u(o, self.rw_address)
        if self.rw_count > 1:
            put(o, b"..", 2)
            put_u(o, self.rw_address + self.rw_count - 1)
        put(o, b" = ", 3)
        shown = self.rw_count if self.rw_count < 16 else 16
        for i in range(shown):
            if i:
                put(o, b", ", 2)
            put_u16(o, be16(self.rw_values + 2 * i))
        if self.rw_count > 16:
            put(o, b", \xe2\x80\xa6 (", 7)
            put_u(o, self.rw_count)
            put(o, b" values)", 8)
        return 0

    cdef int put_rw_fields(self, Buf* o) except -1:
        """A 0x17 request's ``"fields"`` in its JSON line (the decoder's, in its order)."""
        cdef int i
        put(o, b',"fields":{"write_address":', 27)
        put_u(o, self.rw_address)
        put(o, b',"write_count":', 15)
        put_u(o, self.rw_count)
        put(o, b',"write_byte_count":', 20)
        put_u(o, self.rw_bytes)
        put(o, b',"write_values":[', 17)
        for i in range(self.rw_count):
            if i:
                put_c(o, 44)
            put_u16(o, be16(self.rw_values + 2 * i))
        put(o, b"]}", 2)
        return 0

    cdef int rtu_python(self, int64_t index, int d, double ts, const uint8_t* adu, int alen,
                        Pend* req, double latency) except -1:
        """A frame record the reference way: its Frame and Record, formatted by mbmon.format."""
        frame, request = self.rtu_objects(d, ts, adu, alen, req)
        kind = _RECORD_KIND[frame.pdu.kind]
        if req != NULL:
            rec = Record(index, ts, kind, self.rstream, frame, request, req.index, latency)
        else:
            rec = Record(index, ts, kind, self.rstream, frame, None, None, None)
        return self.put_record(rec)

    cdef tuple rtu_objects(self, int d, double ts, const uint8_t* adu, int alen, Pend* req):
        """The reference's Frame of an RTU frame (its PDU decoded as the pairer decodes
        it, given the request) and the request's Frame (``None`` without); counts a
        malformed PDU."""
        stream = self.rstream
        raw = PyBytes_FromStringAndSize(<const char*>adu, alen)
        pdu = decode_pdu(raw[1:alen - 2], d == 1)
        request = None
        if req != NULL:
            req_raw = PyBytes_FromStringAndSize(<const char*>req.raw, req.alen)
            req_pdu = decode_pdu(req_raw[1:req.alen - 2], False)
            request = Frame(req.ts, stream, Direction.C2S, req.unit, None, req_pdu, req_raw, True)
            if _needs_request(pdu, req_pdu):
                pdu = decode_pdu(pdu.raw, True, request=req_pdu)
        frame = Frame(ts, stream, Direction.S2C if d else Direction.C2S, adu[0], None, pdu, raw,
                      True)
        if pdu.malformed:
            self.malformed += 1
        return frame, request


cdef bint _expects_reply_rtu(const uint8_t* adu, int alen) except -1:
    """``pairing.expects_reply`` of a Diagnostics (08) request on a bus: not when its
    sub-function is one the spec leaves unanswered (Force Listen Only Mode)."""
    from mbmon.protocol.pdu import NO_REPLY_DIAGNOSTICS

    pdu = decode_pdu(PyBytes_FromStringAndSize(<const char*>adu + 1, alen - 3), False)
    return pdu.fields.get("sub_function") not in NO_REPLY_DIAGNOSTICS
