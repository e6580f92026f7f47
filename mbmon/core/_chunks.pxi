# The chunk entry of the core (included at the end of _reader.pyx, after _live.pxi:
# it extends _Live, whose per-connection bookkeeping, dry runs, ticks, end and
# hand-over it shares).
#
# A source that knows its streams and directions (the proxy: what crossed each client
# connection, the upstream's answers, the proxy's own answers on a stream of their
# own) hands the core byte chunks -- stream, direction, time, bytes -- and its source
# events, with no link, IP or TCP layer in between. Each chunk and each event is taken
# whole or not at all, as _Live takes packets: whatever the core does not cover is
# known before it changes any state (the MBAP bytes by _Live.chunk_check), and the
# first such item hands the whole run to the reference pipeline (``export``), which
# takes that item and everything after it.
#
# The proxy's observation pipe (mbmon.proxy.remote) is read here directly: a chunk
# record there is a 16-byte head (``CHUNK_HEAD``: tag 'C', the source's stream id,
# the time, the direction, the length) and its bytes, so a whole read of the pipe goes
# through ``pipe`` with no Python object per chunk; other records (tag 'O', pickled:
# streams, events, counters) are cut out by ``pipe_scan`` and given one by one.

DEF PIPE_HEAD = 16     # struct "<cIdBH"
DEF PIPE_OHEAD = 5     # struct "<cI"


def pipe_scan(const uint8_t[::1] buf, Py_ssize_t n):
    """The whole records at the start of ``buf[:n]`` (the observation pipe's format):
    ``(used, chunks, objects)`` -- the bytes they take, how many chunk records, and
    the ``(start, end)`` of each other record's pickle, in order."""
    cdef Py_ssize_t pos = 0, end
    cdef int64_t chunks = 0
    cdef uint32_t length
    objects = []
    if n > buf.shape[0]:
        n = buf.shape[0]
    while n - pos >= PIPE_OHEAD:
        if buf[pos] == 0x43:  # 'C'
            if n - pos < PIPE_HEAD:
                break
            end = pos + PIPE_HEAD + (buf[pos + 14] | (buf[pos + 15] << 8))
            if end > n:
                break
            chunks += 1
            pos = end
            continue
        length = le32(&buf[pos + 1])
        end = pos + PIPE_OHEAD + <Py_ssize_t>length
        if end > n:
            break
        objects.append((pos + PIPE_OHEAD, end))
        pos = end
    return pos, chunks, objects


cdef class _Chunks(_Live):
    """The chunk entry: streams named by the source (:meth:`add_stream`), chunks of
    bytes (:meth:`chunk`, or many at once from the proxy's pipe: :meth:`pipe`) and
    the source's events (:meth:`source_event`) in; lines out through ``write``;
    ``tick``, ``next_deadline``, ``finish`` as _Live's. Each input returns whether the
    core took it; when it did not, ``reason`` says why and :meth:`export_to` gives
    the run to the reference pipeline, which takes that input and the rest."""

    cdef int* cmap                  # the source's stream id -> connection index (-1: none)
    cdef int capcmap
    cdef list ckey                  # connection index -> the source's stream id
    cdef list free_conns            # connection slots of released streams, for reuse
    cdef list closing               # streams that ended with requests pending
    cdef dict joined                # stream id -> the stream whose requests it answers
    cdef dict joins                 # stream id (a client's) -> (its answers' stream, note)
    cdef int npeers                 # the view's robot peers when labels were last cached
    cdef public int64_t chunks      # chunks taken
    cdef public int64_t taken       # pipe records taken (chunks and events)

    def __cinit__(self):
        self.cmap = NULL
        self.capcmap = 0

    def __dealloc__(self):
        free(self.cmap)

    def __init__(self, bint as_json, double timeout, view, write):
        _Live.__init__(self, as_json, timeout, frozenset(), view, write, None)
        self.joined = {}
        self.joins = {}
        self.chunks = 0
        self.taken = 0
        self.ckey = []
        self.free_conns = []
        self.closing = []
        self.npeers = self.peers()

    # ------------------------------------------------------------------ streams

    def add_stream(self, int key, stream):
        """The source's stream ``key`` is ``stream`` (a :class:`~mbmon.model.Stream`
        with the hub's id): a connection of the core's, no bytes held yet."""
        cdef int ci, cap, d, sid = stream.id
        cdef Conn* nc
        cdef LiveConn* lp
        cdef int* mp
        cdef Conn* c
        if key < 0 or sid < 0:
            raise ValueError("stream ids are not negative")
        if key >= self.capcmap:
            cap = self.capcmap * 2 if self.capcmap else 64
            while cap <= key:
                cap *= 2
            mp = <int*>realloc(self.cmap, cap * sizeof(int))
            if mp == NULL:
                raise MemoryError()
            for ci in range(self.capcmap, cap):
                mp[ci] = -1
            self.cmap = mp
            self.capcmap = cap
        if self.free_conns:
            ci = self.free_conns.pop()
        else:
            if self.nconns == self.capconns:
                cap = self.capconns * 2 if self.capconns else 64
                nc = <Conn*>realloc(self.conns, cap * sizeof(Conn))
                if nc == NULL:
                    raise MemoryError()
                self.conns = nc
                self.capconns = cap
            if self.nconns >= self.caplc:
                cap = self.caplc * 2 if self.caplc else 64
                lp = <LiveConn*>realloc(self.lc, cap * sizeof(LiveConn))
                if lp == NULL:
                    raise MemoryError()
                self.lc = lp
                self.caplc = cap
            ci = self.nconns
            self.nconns += 1
            self.ckey.append(-1)
        self.ckey[ci] = key
        c = &self.conns[ci]
        memset(c, 0, sizeof(Conn))
        memset(&self.lc[ci], 0, sizeof(LiveConn))
        c.sid = sid
        for d in range(2):
            c.h[d].nxt = -1
            c.h[d].isn = -1
            c.h[d].fin = -1
        self.cmap[key] = ci
        while len(self._sid_conn) <= sid:
            self._sid_conn.append(-1)
        self._sid_conn[sid] = ci
        while len(self.streams) <= sid:
            self.streams.append(None)
            self.labels.append(None)
            self.heads.append(None)
        self.streams[sid] = stream
        self.ensure_stream(sid)
        return None

    cdef int conn_of_key(self, int64_t key):
        if 0 <= key < self.capcmap:
            return self.cmap[key]
        return -1

    # ------------------------------------------------------------------ chunks

    cdef object take_chunk(self, int64_t key, int d, double ts, const uint8_t* p,
                           Py_ssize_t n):
        """One chunk: None when taken, else why the reference must take it."""
        cdef int ci = self.conn_of_key(key)
        cdef Py_ssize_t left = 0
        if ci < 0:
            return "a chunk of a stream the core was not told of"
        if d != 0 and d != 1:
            return "a serial bus stream (RTU)"
        if self.conns[ci].sid in self.joined:
            return "the proxy's own answers (its stream joined to a client's)"
        if n:
            why = self.chunk_check(ci, d, p, n, &left)
            if why is not None:
                return why
        if self.mcap is not None:  # the chunk on /modbus/raw, before the records it makes
            self.mcap_chunk(self.conns[ci].sid, d, ts, p, n)
        self.on_chunk(ci, d, ts, p, n)
        self.chunks += 1
        return None

    def chunk(self, int key, int d, double ts, const uint8_t[::1] data):
        """A chunk of the source's stream ``key``, direction ``d`` (0: client to
        server, 1: server to client) at ``ts``: whether the core took it."""
        cdef Py_ssize_t n = data.shape[0]
        cdef const uint8_t* p = &data[0] if n else <const uint8_t*>b""
        try:
            why = self.take_chunk(key, d, ts, p, n)
        finally:
            self.flush_out()
        if why is not None:
            self.reason = why
            return False
        return True

    def pipe(self, const uint8_t[::1] buf, Py_ssize_t pos, Py_ssize_t end):
        """The chunk records of the proxy's pipe in ``buf[pos:end]`` (no other record
        there): the offset where the core stopped (``end``: all taken; less: the
        record there is the reference's, ``reason`` says why)."""
        cdef Py_ssize_t length
        cdef double ts
        cdef int64_t key
        cdef const uint8_t* base
        if end > buf.shape[0]:
            end = buf.shape[0]
        if pos < 0 or pos >= end:
            return pos
        base = &buf[0]
        try:
            while end - pos >= PIPE_HEAD and buf[pos] == 0x43:
                length = buf[pos + 14] | (buf[pos + 15] << 8)
                if pos + PIPE_HEAD + length > end:
                    break
                key = le32(base + pos + 1)
                memcpy(&ts, base + pos + 5, 8)
                why = self.take_chunk(key, base[pos + 13], ts, base + pos + PIPE_HEAD, length)
                if why is not None:
                    self.reason = why
                    return pos
                self.taken += 1
                pos += PIPE_HEAD + length
            return pos
        finally:
            self.flush_out()

    # ------------------------------------------------------------------ labels

    cdef int peers(self) except -1:
        peers = getattr(self.view, "_peers", None)
        return 2 if peers is None else len(peers)

    cdef int on_frame(self, int ci, int d, double ts, const uint8_t* adu, int alen) except -1:
        """``_Pass.on_frame``; then, while the view has seen fewer than two peers of the
        robot, whether this frame's label brought the second: the view then names the
        peer in every label (``View._label``), so the labels cached here are made
        again, as the reference's view makes its own again."""
        cdef int i
        _Pass.on_frame(self, ci, d, ts, adu, alen)
        if self.npeers < 2 and self.peers() != self.npeers:
            self.npeers = self.peers()
            for i in range(len(self.labels)):
                self.labels[i] = None
        return 0

    # ------------------------------------------------------------------ events

    def source_event(self, double ts, stream, kind, dict info):
        """A source event (``stream`` the hub's, or None): whether the core took it
        (its record written, its effect on pairing made) -- as the pipeline's
        ``_feed_event`` does."""
        cdef int ci = -1, sid = -1, other
        if stream is not None:
            sid = stream.id
            if sid >= len(self._sid_conn) or self._sid_conn[sid] < 0:
                self.reason = "an event of a stream the core was not told of"
                return False
            ci = self._sid_conn[sid]
        if kind is EventKind.ERROR and stream is None:
            self.reason = "damage reported by the source"
            return False
        if kind is EventKind.GAP:
            self.reason = "a gap in a stream"
            return False
        if kind is EventKind.DISCONNECT and stream is not None:
            if self.conns[ci].h[0].blen or self.conns[ci].h[1].blen:
                self.reason = "an incomplete ADU when its connection ended (noise)"
                return False
            join = self.joins.get(sid)
            if join is not None:
                other = join[0]
                if other < len(self._sid_conn) and self._sid_conn[other] >= 0:
                    ci = self._sid_conn[other]
                    if self.conns[ci].h[0].blen or self.conns[ci].h[1].blen:
                        self.reason = "an incomplete ADU when its connection ended (noise)"
                        return False
        try:
            if kind is EventKind.CONNECT and stream is not None:
                other = -1
                got = info.get("answers_on")
                if type(got) is int and got != sid:
                    other = got
                    note = info.get("note")
                    self.joined[other] = sid
                    self.joins[sid] = (other, note if isinstance(note, str) else None)
            if stream is None:
                self.none_event(ts, kind, info)
            else:
                self.event(ts, sid, kind, info)
            if kind is EventKind.DISCONNECT and stream is not None:
                join = self.joins.pop(sid, None)
                self.ended(sid)
                if join is not None:
                    self.joined.pop(join[0], None)
                    self.ended(join[0])
        finally:
            self.flush_out()
        self.taken += 1
        return True

    # ------------------------------------------------------------------ ended streams

    cdef int ended(self, int sid) except -1:
        """Stream ``sid`` ended (its DISCONNECT): its state is released once no request
        of it waits for an answer (now, or at a later tick), so a proxy that serves
        connection after connection keeps no more than those still open."""
        if sid >= len(self._sid_conn) or self._sid_conn[sid] < 0:
            return 0
        if sid < self.capsp and self.sp[sid].count:
            self.closing.append(sid)
            return 0
        return self.drop_stream(sid)

    cdef int drop_stream(self, int sid) except -1:
        """Forget stream ``sid``: its connection slot (for reuse), held-bytes buffers,
        stream object, labels and log pieces."""
        cdef int ci = self._sid_conn[sid], d, key
        cdef Conn* c = &self.conns[ci]
        for d in range(2):
            free(c.h[d].buf)
            c.h[d].buf = NULL
            c.h[d].blen = 0
            c.h[d].bcap = 0
        key = self.ckey[ci]
        if 0 <= key < self.capcmap and self.cmap[key] == ci:
            self.cmap[key] = -1
        self._sid_conn[sid] = -1
        self.streams[sid] = None
        self.labels[sid] = None
        self.heads[sid] = None
        if self.mtails is not None and sid < len(self.mtails):
            self.mtails[sid] = None
        if self.mprefix is not None:
            for d in range(2):
                if 2 * sid + d < len(self.mprefix):
                    self.mprefix[2 * sid + d] = None
        self.free_conns.append(ci)
        return 0

    cdef int drop_closing(self) except -1:
        """Release the ended streams whose last pending request was answered or timed out."""
        cdef int sid
        if not self.closing:
            return 0
        still = []
        for sid in self.closing:
            if sid < self.capsp and self.sp[sid].count:
                still.append(sid)
            else:
                self.drop_stream(sid)
        self.closing = still
        return 0

    def tick(self, double now):
        """``_Live.tick``, then the ended streams with nothing pending are released."""
        done = _Live.tick(self, now)
        if done == 0:
            self.drop_closing()
        return done

    cdef int none_event(self, double ts, object kind, dict info) except -1:
        """An event of no stream (a notice): its record, formatted by mbmon.format."""
        cdef int64_t index = self.index
        name = kind.value
        self.events[name] = self.events.get(name, 0) + 1
        if ts > self.pl_last:
            self.pl_last = ts
        if ts > self.item_ts:
            self.item_ts = ts
        self.count_record(ts, -1, False)
        ev = Event(ts, None, kind, info)
        return self.put_record(Record(index, ts, RecordKind.EVENT, None, event=ev))

    def streams_held(self):
        """Streams whose state the core holds (not released since their DISCONNECT)."""
        return sum(1 for ci in self._sid_conn if ci >= 0)

    # ------------------------------------------------------------------ the log

    def flush_log(self):
        """The log's message records made so far to its sink (``log_to``), with the
        counters as of their end: after each read of the pipe, each tick, and before
        the hand-over (the sink's own counters then go on from the core's)."""
        if self.mcap is not None:
            self.flush_mcap()
        return None

    # ------------------------------------------------------------------ the hand-over

    def export_to(self, pipeline):
        """Give the run to the reference ``pipeline`` (a fresh
        :class:`~mbmon.pipeline.Pipeline`): its state built from the core's, as if it
        had been fed every chunk and event the core took."""
        self.export_pipeline(pipeline)
        for sid, join in self.joins.items():
            other, note = join
            pipeline.pairer.join(other, sid)
            pipeline._answers_on[sid] = other
            pipeline._joined_notes[other] = (note,) if note else ()
        return None
