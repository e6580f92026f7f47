# The streaming entry of the core (included at the end of _reader.pyx: it extends
# _Pass, whose state and rules it shares).
#
# A live capture cannot be declined "before the first byte": packets arrive while
# lines are written. The rule here: the core takes packets one by one, and each
# packet is taken whole or not at all. Everything that could make the core decline
# a packet is known before the packet changes any state (link and IP headers and
# the flow table by _Pass.packet's own order; the TCP segment by seg_check, a dry
# run of _Pass.segment; idle flows by idle_check). The first packet (or tick, or
# the end) the core does not cover hands the whole run over: ``export`` builds the
# reference dissector's and pipeline's state from the core's (connections, held
# bytes, pending requests, record numbering) and the reference takes that packet
# and everything after it. A whole-run hand-over keeps one record numbering and
# one pairer (timeouts of every stream in one order), so the lines are the
# reference's, byte for byte, in the same order.

DEF LIVE_IDLE = 300.0          # the live dissector's idle timeout (open_dissector)
DEF LIVE_SWEEP_IDLE = 600.0    # PipelineConfig.idle_timeout
DEF LIVE_SWEEP_EVERY = 60.0    # min(max(idle / 10, 0.01), 60.0) for the default
DEF LIVE_HOLE = 2.0            # the live dissector's hole timeout (open_dissector)
DEF MIN_ADU = 8                # the shortest ADU a byte count can hold (MBAP + unit + code)


cdef struct LiveConn:
    double last             # TcpConnection.last: the last segment's time
    double chunk_ts[2]      # the last chunk of each direction (the decoder's _last_ts)
    double input_ts         # the last chunk of the stream (the pipeline's _last_input)


cdef inline bint ack_beyond(int64_t o_nxt, bint o_done, int64_t ack):
    """``_Pass.acked``'s test: the peer acknowledged bytes this direction never showed."""
    cdef int64_t diff
    if o_nxt >= 0 and not o_done:
        diff = (ack - o_nxt) & MASK
        return 0 < diff <= MAX_ACK_JUMP
    return False


cdef class _Live(_Pass):
    """The streaming entry: batches of ``(ts, linktype, bytes)`` in, lines out (through
    ``write``), per-flow state kept across batches; ``tick(now)`` and ``finish(ts)``
    as the hub calls them. Each call returns where the reference must take over
    (see the module comment above) or that the core did it all."""

    cdef object new_stream          # hub.new_stream, or None (ids from 0)
    cdef LiveConn* lc
    cdef int caplc
    cdef double idle_due
    cdef double next_sweep
    cdef public double item_ts      # the latest item (chunk or source event) time
    cdef bint in_segment            # _Pass.segment is changing state
    cdef public str reason          # why the core handed over
    cdef public int64_t packets     # packets taken
    cdef public int64_t modbus_packets
    cdef public int64_t retransmissions
    cdef public int64_t overlaps
    cdef dict holes                 # conn -> when its oldest held segment's wait ends
    cdef list udp_order             # UDP pairs' conn indexes, in creation order
    cdef dict waiting               # conn * 2 + direction: the pipeline's _waiting, in order
    cdef bint keep                  # noise and length 255 taken (the reference decoder inside)
    # ``read`` from a pipe (see "The core on a pipe" below): the file dissector's rules
    # (no idle expiry, no hole timeout, nothing of the dissector's at a tick) and port
    # detection; ``promotion``: what the detector found in the packet the core handed
    # over at (the reference's ``Dissector._promote`` replays it)
    cdef bint file_mode
    cdef public object promotion
    # the reference dissector's counts of other ports (``Dissector._ports``, the same
    # dict: the summary's hint when no Modbus was found), or None: not counted
    cdef public dict port_counts
    # the records of a classic pcap on a pipe, parsed here (``pcap_records``): how many,
    # the last one's time, why the parsing stopped (0: it needs more bytes; 1: the run
    # is handed over at the record at the returned offset; 2: that record's header is
    # corrupt) and that record's length
    cdef public int64_t rec_count
    cdef public double rec_ts
    cdef public int rec_stop
    cdef public Py_ssize_t rec_len
    # ``--since``/``--until`` given as text: resolved at the first record (the console's
    # filter, asked about every record, resolves them there; a pipe has no deciding pass)
    cdef bint f_resolve

    def __cinit__(self):
        self.lc = NULL
        self.caplc = 0

    def __dealloc__(self):
        free(self.lc)

    def __init__(self, bint as_json, double timeout, ports, view, write, new_stream=None,
                 bint keep_noise=False, bint detect=False, bint file_mode=False):
        _Pass.__init__(self, True, as_json, timeout, ports, view, write, detect)
        self.live = True
        self.keep = keep_noise
        self.file_mode = file_mode
        self.promotion = None
        self.port_counts = None
        self.rec_count = 0
        self.rec_ts = 0.0
        self.rec_stop = 0
        self.rec_len = 0
        self.holes = {}
        self.udp_order = []
        self.waiting = {}
        self.new_stream = new_stream
        self.idle_due = INFINITY
        self.next_sweep = -INFINITY
        self.item_ts = -INFINITY
        self.in_segment = False
        self.reason = None
        self.packets = 0
        self.modbus_packets = 0
        self.retransmissions = 0
        self.overlaps = 0

    # ------------------------------------------------------------------ hooks on _Pass

    cdef int alloc_conn(self, const uint8_t* addrs, int alen, int sport, int dport,
                        bint sender_client, bint udp=False) except -1:
        """Every new flow (TCP over IPv4 or IPv6, a UDP pair): its live state, and its
        stream made by the hub (``new_stream``) as the dissector makes it."""
        cdef int ci = _Pass.alloc_conn(self, addrs, alen, sport, dport, sender_client, udp)
        cdef int cap
        cdef LiveConn* p
        if ci >= self.caplc:
            cap = self.caplc * 2 if self.caplc else 64
            while cap <= ci:
                cap *= 2
            p = <LiveConn*>realloc(self.lc, cap * sizeof(LiveConn))
            if p == NULL:
                raise MemoryError()
            self.lc = p
            self.caplc = cap
        memset(&self.lc[ci], 0, sizeof(LiveConn))
        if udp:
            self.udp_order.append(ci)
        if self.new_stream is not None:
            sid = self.conns[ci].sid
            made = self.make_stream(sid)
            s = self.new_stream(made.transport, made.client, made.server)
            if s.id != sid:
                raise RuntimeError("the core's stream ids left the hub's (%d, %d)" % (sid, s.id))
            while len(self.streams) <= sid:
                self.streams.append(None)
                self.labels.append(None)
                self.heads.append(None)
            self.streams[sid] = s
        return ci

    cdef int open_conn(self, bytes key, const uint8_t* addrs, int alen, int sport, int dport,
                       int flags, double ts) except -1:
        cdef int v = _Pass.open_conn(self, key, addrs, alen, sport, dport, flags, ts)
        self.lc[v >> 1].last = ts
        self.idle_soon(ts + LIVE_IDLE)
        return v

    cdef int udp_datagram(self, double ts, const uint8_t* addrs, int alen,
                          const uint8_t[::1] buf, Py_ssize_t l4, Py_ssize_t ip_end) except -1:
        self.udp_room(addrs, alen, buf, l4, ip_end)
        self.modbus_packets += 1
        return _Pass.udp_datagram(self, ts, addrs, alen, buf, l4, ip_end)

    cdef int tcp_flow(self, bytes key, const uint8_t* addrs, int v, double ts, int64_t seq,
                      int flags, bint has_payload, int sport, int dport,
                      int alen=4) except -1:
        """``_Pass.tcp_flow``; a connection the reference reassembles, replaced while
        open, gives its holes up first: declined before anything changes when what
        it holds could pend more requests than the core keeps."""
        cdef int ci
        if v >= 0:
            ci = v >> 1
            if self.conns[ci].tref and not self.conns[ci].closed and (
                    flags & SYN or self.conns[ci].closed) and self.is_new(
                    ci, v & 1, seq, flags, has_payload):
                why = self.room_check(ci, 0)
                if why is not None:
                    raise Declined(why)
        return _Pass.tcp_flow(self, key, addrs, v, ts, seq, flags, has_payload, sport, dport,
                              alen)

    cdef int forget(self, int ci) except -1:
        self.holes.pop(ci, None)
        return _Pass.forget(self, ci)

    cdef int segment(self, int ci, bint from_client, double ts, int64_t seq, int64_t ack,
                     int flags, const uint8_t* p, Py_ssize_t n) except -1:
        why = self.seg_check(ci, from_client, seq, ack, flags, p, n)
        if why is not None:
            raise Declined(why)
        self.modbus_packets += 1
        self.lc[ci].last = ts
        self.in_segment = True
        _Pass.segment(self, ci, from_client, ts, seq, ack, flags, p, n)
        self.in_segment = False
        return 0

    cdef int on_chunk(self, int ci, int d, double ts, const uint8_t* p,
                      Py_ssize_t n) except -1:
        cdef LiveConn* l
        _Pass.on_chunk(self, ci, d, ts, p, n)
        l = &self.lc[ci]
        l.chunk_ts[d] = ts
        l.input_ts = ts
        if self.conns[ci].udp:  # a datagram of the pair (the dissector's _udp_last)
            l.last = ts
            self.idle_soon(ts + LIVE_IDLE)
        if ts > self.item_ts:
            self.item_ts = ts
        if (self.conns[ci].h[d].blen or self.conns[ci].h[d].dstate == 2) and (
                not self.conns[ci].udp and self.buffered(ci, d)):
            self.waiting.setdefault(ci * 2 + d, None)  # the pipeline: a decoder holding bytes waits
        return 0

    cdef Py_ssize_t buffered(self, int ci, int d) except -1:
        """What the direction's decoder holds (the reference decoder's ``buffered``)."""
        if self.conns[ci].h[d].dstate == 2:
            return self.mdecs[ci * 2 + d].buffered
        return self.conns[ci].h[d].blen

    cdef int close_stream(self, int ci, double ts) except -1:
        _Pass.close_stream(self, ci, ts)
        self.waiting.pop(ci * 2, None)  # the pipeline's _close_stream forgets them
        self.waiting.pop(ci * 2 + 1, None)
        return 0

    cdef int event(self, double ts, int sid, object kind, object info) except -1:
        if kind is not EventKind.TIMEOUT and ts > self.item_ts:
            self.item_ts = ts
        return _Pass.event(self, ts, sid, kind, info)

    cdef int detect_segment(self, double ts, bytes addrs, int sport, int dport, int64_t seq,
                            int64_t ack, int flags, bytes payload) except -1:
        """``_Pass.detect_segment``, but a connection found to be Modbus hands the run
        over at this packet: the detector has taken it (``promotion``, which the
        reference dissector replays), the core's state is as before the packet."""
        if self.detector is None:
            return 0
        verdict = self.detector.segment(ts, (addrs, sport, dport), seq, ack, flags, payload)
        if verdict is False:
            self.other_port(sport if sport < dport else dport)
        elif verdict is not True:
            self.promotion = verdict
            raise Declined("Modbus found by port detection on port %d" % min(sport, dport))
        return 0

    cdef int other_port(self, int key) except -1:
        """``Dissector._other_port`` into ``port_counts`` (at most ``MAX_PORTS`` ports)."""
        counts = self.port_counts
        if counts is not None:
            n = counts.get(key)
            if n is not None:
                counts[key] = n + 1
            elif len(counts) < MAX_PORTS:
                counts[key] = 1
        return 0

    def select(self, flt, count, bint show):
        """``_Pass.select``; ``--since``/``--until`` still to be resolved are resolved at
        the first record (``count_record``), where the reference's console resolves
        them (``RecordFilter._time_ok``). Not with ``-c``: its budget, the first
        listener, resolves them at the first frame of the first batch it sees."""
        _Pass.select(self, flt, count, show)
        self.f_resolve = self.f_on and (flt.since_text is not None or flt.until_text is not None)

    cdef int count_record(self, double ts, int sid, bint frame) except -1:
        if self.f_resolve:
            self.f_resolve = False
            self.flt.start_at(ts)
            self.f_since = self.flt.since is not None
            self.f_until = self.flt.until is not None
            self.f_since_v = self.flt.since if self.f_since else 0.0
            self.f_until_v = self.flt.until if self.f_until else 0.0
        return _Pass.count_record(self, ts, sid, frame)

    def frames_left(self):
        """``-c``: the frames still to count (``-1``: no ``-c``), for the reference's
        budget after a hand-over."""
        return self.left

    def port_detector(self):
        """The reference's ``PortDetector`` the core feeds (``None``: detection off)."""
        return self.detector

    # ------------------------------------------------------------------ dry runs

    cdef object chunk_check(self, int ci, int d, const uint8_t* p, Py_ssize_t n,
                            Py_ssize_t* left):
        """What ``on_chunk`` would decline for these bytes of direction ``d``, or None;
        ``left``: the bytes it would then hold."""
        cdef Half* h = &self.conns[ci].h[d]
        cdef Py_ssize_t na = h.blen, total = h.blen + n, pos = 0, frames = 0
        cdef const uint8_t* a = h.buf
        cdef int length, sid = self.conns[ci].sid
        cdef uint8_t hd[6]
        cdef int k
        if h.dstate == 2:  # the reference decoder frames this direction
            return self.room_check(ci, n)
        if na and total > 1 << 24:
            return "an ADU held over more than 16 MiB"
        while total - pos >= 6:
            for k in range(6):
                hd[k] = a[pos + k] if pos + k < na else p[pos + k - na]
            if hd[2] == 0 and hd[3] == 0:
                length = (hd[4] << 8) | hd[5]
                if 2 <= length <= 254:
                    if pos + 6 + length > total:
                        break
                    pos += 6 + length
                    frames += 1
                    continue
            if not self.keep:  # (the proxy's chunk entry: the reference takes them)
                if hd[2] == 0 and hd[3] == 0 and ((hd[4] << 8) | hd[5]) == 255:
                    return "an MBAP length of 255 (decoded, marked malformed)"
                return "bytes that are no MBAP header (noise resynchronisation)"
            # noise, or a length of 255: the reference decoder takes the direction
            return self.room_check(ci, n)
        if total - pos > 1 << 24:
            return "an ADU held over more than 16 MiB"
        if d == 0 and frames:
            if (sid < self.capsp and self.sp[sid].count + frames >= MAX_PENDING_STREAM) or (
                    self.total + frames >= MAX_PENDING_TOTAL):
                return "more requests pending than the core keeps"
        left[0] = total - pos
        return None

    cdef object room_check(self, int ci, Py_ssize_t n):
        """Why the requests ``n`` new bytes of connection ``ci`` and every byte it holds
        (the core's, the reference decoder's, the reference reassembly's) could
        complete might pend more than the core keeps, or None: a bound, one ADU per
        eight bytes, so that what the reference's parts release never meets that
        limit half way through a packet."""
        cdef Conn* c = &self.conns[ci]
        cdef Py_ssize_t most = n + c.h[0].blen + c.h[1].blen, frames
        cdef int d, sid = c.sid
        for d in range(2):
            if c.h[d].dstate == 2:
                dec = self.mdecs[ci * 2 + d]
                most += len(dec._buf) + len(dec._noise)
        if c.tref:
            conn = self.pyconns[ci]
            most += conn._c2s.held_bytes + conn._s2c.held_bytes
        frames = most // MIN_ADU + 1
        if (sid < self.capsp and self.sp[sid].count + frames >= MAX_PENDING_STREAM) or (
                self.total + frames >= MAX_PENDING_TOTAL):
            return "more requests pending than the core keeps"
        return None

    cdef object seg_check(self, int ci, bint from_client, int64_t seq, int64_t ack, int flags,
                          const uint8_t* p, Py_ssize_t n):
        """Why ``_Pass.segment`` would decline this segment half way, or None; nothing
        changes. The common case (in order, clean MBAP) is followed exactly; where
        the reference's reassembly (holes, out of order, a FIN ahead) or its decoder
        (noise, a length of 255, an incomplete ADU at the end) would take part, the
        requests the segment could complete are bounded (``room_check``). What still
        declines: a reset before a FIN was reached, the core's limits."""
        cdef Conn* c = &self.conns[ci]
        cdef int d = 0 if from_client else 1
        cdef int64_t h_fin = c.h[d].fin, o_fin = c.h[1 - d].fin
        cdef Py_ssize_t left = 0
        if c.tref:
            return self.room_check(ci, n)
        if not flags & 0x07 and c.h[d].nxt == seq and h_fin < 0:
            if c.closed:
                return None  # payload after the end: counted and dropped
            if flags & ACK and ack_beyond(c.h[1 - d].nxt, c.h[1 - d].done, ack):
                return self.room_check(ci, n)  # a gap: the other direction's decoder resets
            if n:
                return self.chunk_check(ci, d, p, n, &left)
            return None
        if c.closed:
            return None
        if flags & RST and ((h_fin >= 0 and not c.h[d].done) or (
                o_fin >= 0 and not c.h[1 - d].done)):
            return "a reset before a FIN was reached (a gap)"
        return self.room_check(ci, n)

    cdef int udp_room(self, const uint8_t* addrs, int alen, const uint8_t[::1] buf,
                      Py_ssize_t l4, Py_ssize_t ip_end) except -1:
        """``room_check`` for a datagram (raised: nothing has changed yet)."""
        cdef Py_ssize_t frames = (ip_end - l4) // MIN_ADU + 1
        cdef int sid = -1
        got = self.udp_pairs.get(bytes(addrs[:2 * alen]) + bytes(buf[l4:l4 + 4]))
        if got is not None:
            sid = self.conns[got >> 1].sid
        if (0 <= sid < self.capsp and self.sp[sid].count + frames >= MAX_PENDING_STREAM) or (
                self.total + frames >= MAX_PENDING_TOTAL):
            raise Declined("more requests pending than the core keeps")
        return 0

    # ------------------------------------------------------------------ holes (the live dissector's)

    cdef object hole_watcher(self):
        return None if self.file_mode else self  # a file's holes never time out

    def held(self, conn, double ts):
        """Watcher hook of a connection the reference reassembles: it holds bytes
        behind a hole since ``ts`` (given up ``LIVE_HOLE`` s later, as the live
        dissector gives them up)."""
        cdef int ci = self._sid_conn[conn.stream.id]
        cdef double due = ts + LIVE_HOLE
        if ci not in self.holes:
            self.holes[ci] = due
            if due < self.due:
                self.due = due

    def closed(self, conn, double ts):
        """Watcher hook: the connection ended (``ref_out`` closes it in the core)."""
        self.holes.pop(self._sid_conn[conn.stream.id], None)

    cdef int dissector_tick(self, double now) except -1:
        """The live dissector's ``_tick``, in its order: holes waited for ``LIVE_HOLE``
        s given up (the reference reassembly's own ``expire_holes``), flows idle for
        ``LIVE_IDLE`` s expired (``expire_idle``), then the closed connections'
        linger. Declined before anything changes when what the holes or the expired
        connections release could pend more requests than the core keeps."""
        cdef int ci
        cdef double first = INFINITY
        for ci, due in self.holes.items():
            if due <= now and ci in self.pyconns:
                why = self.room_check(ci, 0)
                if why is not None:
                    raise Declined(why)
        if now >= self.idle_due:
            why = self.idle_check(now)
            if why is not None:
                raise Declined(why)
        for ci, due in list(self.holes.items()):
            if due > now or ci not in self.holes:
                continue
            conn = self.pyconns.get(ci)
            again = None
            out = []
            if conn is not None:
                again = conn.expire_holes(now, LIVE_HOLE, out)
            if again is None:
                self.holes.pop(ci, None)
            else:
                self.holes[ci] = again
            if out:
                self.ref_out(ci, out)
                self.ref_done(ci)
        if now >= self.idle_due:
            self.expire_idle(now)
        _Pass.dissector_tick(self, now)
        for due in self.holes.values():
            if due < first:
                first = due
        if first < self.due:
            self.due = first
        if self.idle_due < self.due:
            self.due = self.idle_due
        return 0

    cdef int idle_soon(self, double due) except -1:
        """The idle scan is due at ``due`` (the first flow): the dissector's tick then
        (never for a file's dissector: its flows do not expire for idleness)."""
        if self.idle_due == INFINITY and not self.file_mode:
            self.idle_due = due
            if due < self.due:
                self.due = due
        return 0

    cdef object idle_check(self, double now):
        """Why ``expire_idle`` at ``now`` would stop half way (nothing changes), or None."""
        cdef double limit = now - LIVE_IDLE
        cdef int ci
        cdef Conn* c
        for ci in self.open_order:
            c = &self.conns[ci]
            if not c.open_ or self.lc[ci].last > limit:
                continue
            if c.tref:
                why = self.room_check(ci, 0)
                if why is not None:
                    return why
            elif (c.h[0].fin >= 0 and not c.h[0].done) or (c.h[1].fin >= 0 and not c.h[1].done):
                return "a FIN not reached when its connection went idle (a gap)"
        return None

    cdef int expire_idle(self, double now) except -1:
        """``FlowTable._expire_idle``: every connection, then every UDP pair, with no
        packet for ``LIVE_IDLE`` s ends (a DISCONNECT ``how="idle"`` stamped when it
        expired, its decoders flushed; its keys dropped at once); the next scan at
        the earliest survivor's expiry, not sooner than a second from now."""
        cdef double limit = now - LIVE_IDLE, first = INFINITY, last, ts
        cdef int ci
        cdef Conn* c
        reason = "no packets for %g s" % LIVE_IDLE
        for ci in list(self.open_order):
            c = &self.conns[ci]
            if not c.open_:
                continue
            last = self.lc[ci].last
            if last > limit:
                if last < first:
                    first = last
                continue
            ts = last + LIVE_IDLE
            if c.tref:  # the reference reassembly gives its holes up and ends it
                conn = self.pyconns.pop(ci)
                c.tref = False
                out = []
                conn.expire(ts, out, reason)
                self.ref_out(ci, out)
            elif not c.closed:
                if c.connected or c.h[0].nxt >= 0 or c.h[1].nxt >= 0:  # it showed something
                    info = {"how": "idle", "reason": reason}
                    if c.fin_by:
                        info["by"] = "client" if c.fin_by == 1 else "server"
                        info["half_closed"] = True
                    self.event(ts, c.sid, EventKind.DISCONNECT, info)
                    self.close_stream(ci, ts)
            # forgotten at once (no linger): the dissector's _forget
            c = &self.conns[ci]
            c.closed = True
            if c.open_:
                c.open_ = False
                self.nopen -= 1
            for i, item in enumerate(self.closed_fifo):
                if item[0] == ci:
                    del self.closed_fifo[i]
                    break
            self.holes.pop(ci, None)
            self.forget(ci)
        for ci in list(self.udp_order):
            last = self.lc[ci].last
            if last > limit:
                if last < first:
                    first = last
                continue
            ts = last + LIVE_IDLE
            self.udp_order.remove(ci)
            c = &self.conns[ci]
            for k in [k for k, v in self.udp_pairs.items() if v >> 1 == ci]:
                del self.udp_pairs[k]
            self.event(ts, c.sid, EventKind.DISCONNECT, {"how": "idle", "reason": reason})
            self.close_stream(ci, ts)
        if first == INFINITY:
            self.idle_due = INFINITY
        else:
            self.idle_due = first + LIVE_IDLE
            if self.idle_due < now + 1.0:
                self.idle_due = now + 1.0
        return 0

    # ------------------------------------------------------------------ the entry

    def feed(self, list batch):
        """Take the packets of ``batch`` in order; return how many were taken (all:
        ``len(batch)``; fewer: the reference must take over from that packet, whose
        effects are none yet; ``reason`` says why)."""
        cdef Py_ssize_t i, count = len(batch)
        cdef double ts
        cdef int link
        cdef bytes data
        try:
            for i in range(count):
                item = batch[i]
                ts = item[0]
                link = item[1]
                data = item[2]
                try:
                    self.packet(ts, link, data, 0, len(data))
                except Declined as exc:
                    if self.in_segment:
                        raise RuntimeError("the core declined a segment it had begun: %s"
                                           % exc) from None
                    self.reason = str(exc)
                    return i
                self.packets += 1
            return count
        finally:
            self.flush_out()

    def pcap_records(self, bytes data, Py_ssize_t pos, bint big, double divisor, int header,
                     int link, Py_ssize_t limit, list into=None):
        """The whole records of a classic pcap in ``data`` from ``pos`` (a record's start),
        as the reference's pump reads them (``_pcap_pump``: the same checks, times and
        counts): each taken by the core, or with ``into`` appended to it as
        ``(ts, link type, bytes, 0)`` for the reference dissector. The offset where it
        stopped; ``rec_stop`` says why (see the attributes). A record the core does not
        cover is not taken (``reason``), unless port detection took it
        (``promotion``): then the offset is past it."""
        cdef const uint8_t[::1] buf = data
        cdef Py_ssize_t size = len(data), start, end, caplen
        cdef double ts
        self.rec_stop = 0
        try:
            while size - pos >= header:
                caplen = rd32(&buf[pos + 8], big)
                if caplen > limit:
                    self.rec_stop = 2
                    self.rec_len = caplen
                    return pos
                end = pos + header + caplen
                if end > size:
                    return pos
                ts = <double>rd32(&buf[pos], big) + <double>rd32(&buf[pos + 4], big) / divisor
                start = pos + header
                if into is not None:
                    into.append((ts, link, data[start:end], 0))
                else:
                    try:
                        self.packet(ts, link, buf, start, end)
                    except Declined as exc:
                        if self.in_segment:
                            raise RuntimeError("the core declined a segment it had begun: %s"
                                               % exc) from None
                        self.reason = str(exc)
                        self.rec_stop = 1
                        if self.promotion is None:
                            return pos
                        self.rec_count += 1
                        self.rec_ts = ts
                        return end
                    self.packets += 1
                self.rec_count += 1
                self.rec_ts = ts
                pos = end
            return pos
        finally:
            if into is None:
                self.flush_out()

    def tick(self, double now):
        """The hub's tick at ``now``: 0 the core did it; 1 the reference must take over
        before it (its dissector's tick first); 2 the core did the dissector's part and
        the reference's pipeline does the rest (the hub ticks it next)."""
        cdef int ci, d
        try:
            if now >= self.due and not self.file_mode:  # a file's dissector is never ticked
                try:
                    self.dissector_tick(now)
                except Declined as exc:  # before anything changed
                    self.reason = str(exc)
                    return 1
            if now >= self.next_sweep:
                for ci in range(self.nconns):
                    for d in range(2):
                        if (self.conns[ci].h[d].blen or self.conns[ci].h[d].dstate == 2) and (
                                self.lc[ci].input_ts < now - LIVE_SWEEP_IDLE):
                            self.reason = "an incomplete ADU idle for %g s" % LIVE_SWEEP_IDLE
                            return 2
                self.next_sweep = now + LIVE_SWEEP_EVERY
                # the pipeline forgets streams idle that long (nothing held: no record)
                for ci in range(self.nconns):
                    if self.lc[ci].input_ts < now - LIVE_SWEEP_IDLE and not self.conns[ci].udp and (
                            self.conns[ci].h[0].dstate or self.conns[ci].h[1].dstate):
                        self.close_stream(ci, self.lc[ci].input_ts)
            why = self.settle(now)
            if why is not None:
                self.reason = why
                return 2
            self.pair_tick(now)
            return 0
        finally:
            self.flush_out()

    cdef object settle(self, double now):
        """The pipeline's decoders settle what they hold after a silence (``tick``), in
        the order of its waiting list (``waiting``: a direction joins it when its
        decoder holds bytes after a chunk, leaves it at a tick that finds nothing
        held and nothing due, or when its stream ends): only the reference decoders
        framing a direction after noise have anything to settle. Why the pipeline's
        part goes to the reference instead (nothing changed), or None."""
        cdef int key, ci, d
        for key in self.waiting:
            if self.conns[key >> 1].h[key & 1].dstate == 2:
                deadline = self.mdecs[key].next_deadline()
                if deadline is not None and deadline <= now:
                    why = self.room_check(key >> 1, 0)
                    if why is not None:
                        return why
        for key in list(self.waiting):
            ci = key >> 1
            d = key & 1
            deadline = None
            if self.conns[ci].h[d].dstate == 2:
                dec = self.mdecs[key]
                deadline = dec.next_deadline()
                if deadline is not None and deadline <= now:
                    items = dec.tick(now)
                    self.ref_resync(ci, d, dec)
                    self.ref_items(ci, d, items)
                    deadline = dec.next_deadline() if self.conns[ci].h[d].dstate == 2 else None
            if deadline is None and not self.buffered(ci, d):
                del self.waiting[key]
        return None

    def next_deadline(self):
        """When a tick next has something to do (the dissector's and the pairer's
        deadlines), or None."""
        cdef double best = self.due
        cdef int s = self.ahead
        if self.idle_due < best:
            best = self.idle_due
        for dec in self.mdecs.values():
            deadline = dec.next_deadline()
            if deadline is not None and deadline < best:
                best = deadline
        while s >= 0:
            if self.sp[s].count and self.pool[self.sp[s].head].ts + self.timeout < best:
                best = self.pool[self.sp[s].head].ts + self.timeout
            s = self.sp[s].anext
        return None if best == INFINITY else best

    def finish(self, double now):
        """The end of input at the hub's time ``now`` (the dissector's ``finish``, then
        the pipeline's): holes given up and half-closed connections ended, the
        decoders flushed in the order they were made (an incomplete ADU: noise),
        every pending request timed out. False (nothing done) when the reference
        must take over first (a FIN not reached, the core's limits). A file's
        dissector ends at ``now`` itself (its last record's time)."""
        cdef int ci, s, e, nxt
        cdef Conn* c
        cdef double ts = now if now > self.item_ts or self.file_mode else self.item_ts
        for ci in range(self.nconns):
            c = &self.conns[ci]
            if c.h[0].blen or c.h[1].blen or c.h[0].dstate == 2 or c.h[1].dstate == 2 or (
                    c.tref):
                why = self.room_check(ci, 0)
                if why is not None:
                    self.reason = why
                    return False
            if c.open_ and not c.closed and not c.tref and (
                    (c.h[0].fin >= 0 and not c.h[0].done) or (c.h[1].fin >= 0 and not c.h[1].done)):
                self.reason = "a FIN not reached at the end (a gap)"
                return False
        try:
            for ci in list(self.open_order):
                c = &self.conns[ci]
                if not c.open_ or c.closed:
                    continue
                if c.tref:  # holes given up ("end-of-capture"), a half-closed end
                    self.ref_finish(ci, ts, "end-of-capture")
                    continue
                if c.fin_by:
                    self.event(ts, c.sid, EventKind.DISCONNECT,
                               {"how": "fin", "by": "client" if c.fin_by == 1 else "server",
                                "half_closed": True})
                    self.close_stream(ci, ts)
                    self.closed_conn(ci, ts)
            when = self.pl_last
            for key in self.decoders_made():
                self.flush_dir(key >> 1, key & 1, when)
            s = self.ahead
            while s >= 0:
                nxt = self.sp[s].anext
                while self.sp[s].count:
                    e = self.sp[s].head
                    self.timeout_record(self.due_by(e, self.pl_last), e)
                s = nxt
        finally:
            self.flush_out()
        return True

    def open_connections(self):
        """Connections open now (the dissector's ``open_connections``)."""
        return self.nopen

    def streams_made(self):
        """Streams made so far (the dissector's ``streams``)."""
        return len(self._sid_conn)

    # ------------------------------------------------------------------ the hand-over

    cdef object py_conn(self, int ci, dissector, cls, int limit):
        """Connection ``ci`` as the reference's ``TcpConnection``."""
        cdef Conn* c = &self.conns[ci]
        cdef int d
        conn = cls(self.stream_obj(c.sid), limit=limit, stats=dissector.tcp_stats,
                   watcher=dissector)
        for d in range(2):
            half = conn._s2c if d else conn._c2s
            half.nxt = None if c.h[d].nxt < 0 else c.h[d].nxt
            half.isn = None if c.h[d].isn < 0 else c.h[d].isn
            half.fin = None if c.h[d].fin < 0 else c.h[d].fin
            half.done = bool(c.h[d].done)
        conn.connected = bool(c.connected)
        conn.closed = bool(c.closed)
        conn.fin_by = None if c.fin_by == 0 else ("client" if c.fin_by == 1 else "server")
        conn.last = self.lc[ci].last
        return conn

    cdef object key_of(self, int ci):
        """The reference's flow key of connection ``ci`` (client to server)."""
        cdef Conn* c = &self.conns[ci]
        return (bytes(c.caddr[:c.alen]) + bytes(c.saddr[:c.alen]), c.cport, c.sport)

    cdef object conn_out(self, int ci, dict conns, dissector, cls, int limit):
        """Connection ``ci`` as the dissector's: the reference reassembly the core
        already uses for it (now watched by the dissector), or one made from the
        core's state."""
        conn = conns.get(ci)
        if conn is not None:
            return conn
        conn = self.pyconns.get(ci)
        if conn is not None:
            conn.watcher = dissector
            conn.stats = dissector.tcp_stats
            conn.last = self.lc[ci].last
        else:
            conn = self.py_conn(ci, dissector, cls, limit)
        conns[ci] = conn
        return conn

    def export(self, dissector, pipeline):
        """Give the run to the reference: build ``dissector``'s (a fresh
        :class:`~mbmon.sources.dissect.Dissector` with the same ``new_stream``) and
        ``pipeline``'s (a fresh :class:`~mbmon.pipeline.Pipeline`) state from the
        core's, as if they had read every packet the core took: connections (the
        reference reassemblies the core used, with their holes' deadlines), UDP
        pairs, flow keys (IPv4 and IPv6), then the pipeline's part."""
        from mbmon.sources.flows import _TCP_HOLD_LIMIT
        from mbmon.sources.tcpflow import TcpConnection

        cdef int ci, alen, v
        conns = {}
        for ci in self.open_order:
            if self.conns[ci].open_:
                conn = self.conn_out(ci, conns, dissector, TcpConnection, _TCP_HOLD_LIMIT)
                dissector.connections[conn] = self.key_of(ci)
        for ci, until in self.closed_fifo:
            conn = self.conn_out(ci, conns, dissector, TcpConnection, _TCP_HOLD_LIMIT)
            dissector._closed[conn] = (self.key_of(ci), until)
        for k, v in self.flows.items():
            ci = v >> 1
            alen = (len(k) - 4) // 2
            conn = self.conn_out(ci, conns, dissector, TcpConnection, _TCP_HOLD_LIMIT)
            dissector.tcp[(k[:2 * alen], (k[2 * alen] << 8) | k[2 * alen + 1],
                           (k[2 * alen + 2] << 8) | k[2 * alen + 3])] = (conn, bool(v & 1))
        for ci, due in self.holes.items():
            if ci in conns:
                dissector._holes[conns[ci]] = due
        for k, v in self.udp_pairs.items():
            ci = v >> 1
            alen = (len(k) - 4) // 2
            stream = self.stream_obj(self.conns[ci].sid)
            key = (k[:2 * alen], (k[2 * alen] << 8) | k[2 * alen + 1],
                   (k[2 * alen + 2] << 8) | k[2 * alen + 3])
            dissector.udp[key] = (stream, Direction.C2S if v & 1 else Direction.S2C)
            if stream.id not in dissector._udp_keys:
                dissector._udp_keys[stream.id] = (key, stream)
                dissector._udp_last[stream.id] = self.lc[ci].last
        dissector._idle_due = self.idle_due
        dissector._set_due()
        dissector.next_id = len(self._sid_conn)
        dissector.modbus_packets += self.modbus_packets
        self.export_pipeline(pipeline)
        return None

    cdef list decoders_made(self):
        """``dec_order`` as the pipeline's decoders stand: each direction once, where its
        latest decoder was made (a slot the chunk entry reused, a stream begun again)."""
        cdef int key
        seen = set()
        order = []
        for key in reversed(self.dec_order):
            if key not in seen:
                seen.add(key)
                order.append(key)
        order.reverse()
        return order

    cdef int export_pipeline(self, pipeline) except -1:
        """The pipeline's part of :meth:`export`: record numbering, its clocks, the
        decoders in the order they were made (the bytes the core holds with their
        arrival times; a reference decoder framing a direction after noise, as it
        is), the pending requests with their record indexes (in the pairer's order)."""
        cdef int ci, d, s, e, key
        cdef Conn* c
        cdef Pend* p
        pipeline._index = self.index
        pipeline._next_tick = self.next_tick
        pipeline._last_ts = self.pl_last
        pipeline._next_sweep = self.next_sweep
        for key in self.decoders_made():
            ci = key >> 1
            d = key & 1
            c = &self.conns[ci]
            if c.h[d].dstate == 0 or self._sid_conn[c.sid] != ci:  # none, or a released slot
                continue
            stream = self.stream_obj(c.sid)
            direction = Direction.S2C if d else Direction.C2S
            if c.h[d].dstate == 2:
                pipeline._streams[c.sid] = stream
                pipeline._decoders[(c.sid, direction)] = self.mdecs[key]
            else:
                dec = pipeline._decoder(stream, direction)
                if c.h[d].blen:
                    dec.feed(PyBytes_FromStringAndSize(<const char*>c.h[d].buf, c.h[d].blen),
                             c.h[d].bts)
                dec._last_ts = self.lc[ci].chunk_ts[d]
            pipeline._last_input[c.sid] = self.lc[ci].input_ts
        for key in self.waiting:
            c = &self.conns[key >> 1]
            if self._sid_conn[c.sid] != key >> 1:
                continue
            direction = Direction.S2C if key & 1 else Direction.C2S
            dec = pipeline._decoders.get((c.sid, direction))
            if dec is not None:
                pipeline._waiting[(c.sid, direction)] = dec
        pending = pipeline.pairer._pending
        s = self.ahead
        while s >= 0:
            e = self.sp[s].head
            while e >= 0:
                p = &self.pool[e]
                stream = self.stream_obj(p.sid)
                raw = PyBytes_FromStringAndSize(<const char*>p.raw, p.alen)
                frame = Frame(p.ts, stream, Direction.C2S, p.unit, p.tid,
                              decode_pdu(raw[7:], False), raw, None)
                pending.setdefault(p.sid, {})[(p.tid, p.unit)] = frame
                pipeline.pairer._total += 1
                pipeline._pending_index[id(frame)] = p.index
                e = p.next
            s = self.sp[s].anext
        return 0



# --------------------------------------------------------------------------- the capture side

from libc.stdint cimport uint16_t

cdef extern from "<sys/uio.h>":
    cdef struct iovec:
        void* iov_base
        size_t iov_len

cdef extern from "<sys/socket.h>":
    ctypedef unsigned int socklen_t
    cdef struct msghdr:
        void* msg_name
        socklen_t msg_namelen
        iovec* msg_iov
        size_t msg_iovlen
        void* msg_control
        size_t msg_controllen
        int msg_flags
    cdef struct mmsghdr:
        msghdr msg_hdr
        unsigned int msg_len
    cdef struct cmsghdr:
        size_t cmsg_len
        int cmsg_level
        int cmsg_type
    int recvmmsg(int fd, mmsghdr* vec, unsigned int vlen, int flags, void* timeout) nogil
    cmsghdr* CMSG_FIRSTHDR(msghdr* m)
    cmsghdr* CMSG_NXTHDR(msghdr* m, cmsghdr* c)
    unsigned char* CMSG_DATA(cmsghdr* c)
    size_t CMSG_LEN(size_t n)
    int MSG_DONTWAIT
    int SOL_SOCKET

cdef extern from "<netpacket/packet.h>":
    cdef struct sockaddr_ll:
        unsigned short sll_family
        unsigned short sll_protocol
        int sll_ifindex
        unsigned short sll_hatype
        unsigned char sll_pkttype

cdef extern from "<errno.h>":
    int errno
    int EAGAIN
    int EWOULDBLOCK
    int EINTR

DEF RX_BATCH = 64
DEF RX_SNAP = 65535        # what PacketCapture asked of recvmsg
DEF RX_CTRL = 512
DEF RX_SO_TIMESTAMPNS = 35
DEF RX_SOL_PACKET = 263
DEF RX_PACKET_AUXDATA = 8
DEF RX_PACKET_OUTGOING = 4
DEF RX_VLAN_VALID = 0x10
DEF RX_VLAN_TPID_VALID = 0x40

import time as _time


cdef class _Receiver:
    """Packets of an ``AF_PACKET`` socket, many per system call (``recvmmsg``): what
    ``PacketCapture``'s reader took one ``recvmsg`` at a time through scapy's
    ``_recv_raw``, the same bytes and the same times: the kernel's ``SO_TIMESTAMPNS``
    (``sec + nsec * 1e-9``, else the clock), a VLAN tag the kernel took off put back
    from ``PACKET_AUXDATA``, outgoing loopback copies left out."""

    cdef int fd
    cdef int linktype
    cdef bint loopback
    cdef char* data
    cdef char* ctrl
    cdef mmsghdr msgs[RX_BATCH]
    cdef iovec iov[RX_BATCH]
    cdef sockaddr_ll names[RX_BATCH]

    def __cinit__(self, int fd, int linktype, bint loopback):
        self.data = <char*>malloc(RX_BATCH * RX_SNAP)
        self.ctrl = <char*>malloc(RX_BATCH * RX_CTRL)
        if self.data == NULL or self.ctrl == NULL:
            raise MemoryError()
        self.fd = fd
        self.linktype = linktype
        self.loopback = loopback

    def __dealloc__(self):
        free(self.data)
        free(self.ctrl)

    def read(self, list batch, int room):
        """Append up to ``room`` packets ``(ts, linktype, bytes)`` to ``batch``; the
        number of messages the kernel gave (0: none waiting). OSError on failure."""
        cdef int i, n, want = room if room < RX_BATCH else RX_BATCH
        cdef msghdr* m
        cdef cmsghdr* c
        cdef const unsigned char* cd
        cdef double ts
        cdef bint stamped
        cdef int64_t sec, nsec
        cdef uint32_t status
        cdef unsigned int tci, tpid, length
        cdef uint16_t half16
        cdef char* base
        cdef bytes pkt
        if want <= 0:
            return 0
        for i in range(want):
            self.iov[i].iov_base = self.data + i * RX_SNAP
            self.iov[i].iov_len = RX_SNAP
            m = &self.msgs[i].msg_hdr
            m.msg_name = &self.names[i]
            m.msg_namelen = sizeof(sockaddr_ll)
            m.msg_iov = &self.iov[i]
            m.msg_iovlen = 1
            m.msg_control = self.ctrl + i * RX_CTRL
            m.msg_controllen = RX_CTRL
            m.msg_flags = 0
            self.msgs[i].msg_len = 0
        with nogil:
            n = recvmmsg(self.fd, self.msgs, want, MSG_DONTWAIT, NULL)
        if n < 0:
            if errno == EAGAIN or errno == EWOULDBLOCK or errno == EINTR:
                return 0
            raise OSError(errno, os_strerror(errno))
        for i in range(n):
            length = self.msgs[i].msg_len
            if self.loopback and self.names[i].sll_pkttype == RX_PACKET_OUTGOING:
                continue  # the same packet comes back in
            if length == 0:
                continue
            m = &self.msgs[i].msg_hdr
            base = self.data + i * RX_SNAP
            stamped = False
            ts = 0.0
            pkt = None
            c = CMSG_FIRSTHDR(m)
            while c != NULL:
                cd = CMSG_DATA(c)
                if c.cmsg_level == RX_SOL_PACKET and c.cmsg_type == RX_PACKET_AUXDATA:
                    if c.cmsg_len >= CMSG_LEN(20):
                        memcpy(&status, cd, 4)
                        memcpy(&half16, cd + 16, 2)  # tp_vlan_tci, host order
                        tci = half16
                        memcpy(&half16, cd + 18, 2)  # tp_vlan_tpid
                        tpid = half16
                        if tci != 0 or status & RX_VLAN_VALID:
                            if not status & RX_VLAN_TPID_VALID:
                                tpid = 0x8100
                            head = PyBytes_FromStringAndSize(base, 12 if length > 12 else length)
                            tag = bytes(((tpid >> 8) & 255, tpid & 255, (tci >> 8) & 255,
                                         tci & 255))
                            rest = (PyBytes_FromStringAndSize(base + 12, length - 12)
                                    if length > 12 else b"")
                            pkt = head + tag + rest
                elif c.cmsg_level == SOL_SOCKET and c.cmsg_type == RX_SO_TIMESTAMPNS:
                    if c.cmsg_len == CMSG_LEN(16):
                        memcpy(&sec, cd, 8)
                        memcpy(&nsec, cd + 8, 8)
                        ts = <double>sec + <double>nsec * 1e-9
                        stamped = True
                    elif c.cmsg_len == CMSG_LEN(8):
                        ts = <double>(<int*>cd)[0] + <double>(<int*>cd)[1] * 1e-9
                        stamped = True
                c = CMSG_NXTHDR(m, c)
            if pkt is None:
                pkt = PyBytes_FromStringAndSize(base, length)
            batch.append((ts if stamped else _time.time(), self.linktype, pkt))
        return n


cdef str os_strerror(int code):
    import os
    return os.strerror(code)
