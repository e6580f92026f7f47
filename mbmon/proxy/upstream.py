"""The upstream side for a Modbus/TCP server: :class:`TcpLink`, one upstream
connection (a client's own, or the one every client shares). It connects and
reconnects with backoff (0x0A while the upstream is unavailable), takes the
requests, times them out (0x0B) and, per client, renews the connection after a
gateway timeout so that a late answer can never reach a later request. Its
requests in flight and its answer path are :class:`~mbmon.proxy.link.LinkBase`'s.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict

from mbmon.model import Direction
from mbmon.protocol.mbap import MbapDecoder
from mbmon.proxy.config import GATEWAY_PATH_UNAVAILABLE, GATEWAY_TARGET_FAILED
from mbmon.proxy.keepalive import connection_error, keepalive
from mbmon.proxy.link import LinkBase, Pending, UpstreamSocket

__all__ = ["LINGER", "MAX_RETIRED", "TcpLink"]

#: A client's upstream connection renewed after a gateway timeout stays open this many
#: ``timeout``\ s (while it owes answers, longer), so that the late answer is seen and
#: logged as dropped; at most ``MAX_RETIRED`` such connections per client (the oldest
#: closes first).
LINGER = 4
MAX_RETIRED = 2


class TcpLink(LinkBase):
    """One upstream connection to a Modbus/TCP server (a client's own, or the shared
    one): connects and reconnects with backoff, keeps the requests in flight and
    their timers."""

    # -------------------------------------------------------------- connecting

    def connect(self) -> None:
        """Start a connection attempt (the loop's task does the waiting)."""
        if self.state in ("connecting", "up", "closed"):
            return
        self.state = "connecting"
        self.engine.loop.create_task(self._connect())

    async def _connect(self) -> None:
        engine = self.engine
        cfg = engine.config
        loop = engine.loop
        try:
            _transport, proto = await asyncio.wait_for(
                loop.create_connection(
                    lambda: UpstreamSocket(self), cfg.upstream_host, cfg.upstream_port
                ),
                timeout=cfg.timeout,
            )
        except (TimeoutError, OSError) as exc:
            self._failed(connection_error(exc))
            return
        if self.state == "closed":
            if proto.transport is not None:
                proto.transport.close()
            return
        self.proto = proto  # type: ignore[assignment]
        self.state = "up"
        if proto.transport is not None:
            sock = proto.transport.get_extra_info("socket")
            if sock is not None:
                keepalive(sock)
        self.decoder = MbapDecoder(self.decoding_stream(), Direction.S2C)
        self.received = self.consumed = 0
        self.late.clear()  # what the old connection owed can never arrive on this one
        self.streaming = None
        self.streamed = 0
        self.tail = b""
        engine.stats.upstream_connects += 1
        engine.upstream_state = "up"
        if self.failing:
            self.failing = False
            self.notice(f"upstream {cfg.upstream} is back", {"upstream": cfg.upstream})
        self.backoff = cfg.backoff_min
        queued, self.queued = self.queued, []
        out = []
        for entry in queued:
            if entry.client.closed:
                self.forget(entry)
                continue
            self._track(entry)
            out.append(entry.raw)
        if out:
            self.proto.transport.write(b"".join(out))  # type: ignore[union-attr]

    def _failed(self, why: str) -> None:
        engine = self.engine
        cfg = engine.config
        if self.state == "closed":
            return
        self.state = "down"
        engine.stats.upstream_failures += 1
        engine.upstream_state = f"unavailable ({why})"
        self.next_attempt = engine.loop.time() + self.backoff
        wait = self.backoff
        self.backoff = min(self.backoff * 2, cfg.backoff_max)
        if not self.failing or why != self.last_error:
            self.notice(
                f"upstream {cfg.upstream} unavailable ({why}): answering 0x0A, "
                f"next try in {wait:.2f} s",
                {"upstream": cfg.upstream, "reason": why},
            )
        self.failing = True
        self.last_error = why
        queued, self.queued = self.queued, []
        for entry in queued:
            self._cancel_timer(entry)
            engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)

    # -------------------------------------------------------------- requests

    def submit(self, entry: Pending) -> bytes | None:
        """Take a request: the bytes to write upstream now, or ``None`` (queued
        for the connection, or answered 0x0A already)."""
        state = self.state
        if state == "up":
            if entry.deadline is None:  # _track and _start_timer inline: every request
                pending = self.pending
                lst = pending.get(entry.utid)
                if lst is None:
                    pending[entry.utid] = [entry]
                else:
                    lst.append(entry)
                entry.client.outstanding.add(entry)
                entry.link = self
                self.engine.arm(entry)
            else:
                self._track(entry)
            return entry.raw
        if state == "down" and self.engine.loop.time() >= self.next_attempt:
            self.connect()
            state = self.state
        if state == "connecting":
            self.queued.append(entry)
            self._start_timer(entry)
            return None
        self.engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
        return None

    def assign_tid(self, tid: int) -> int:
        """The upstream transaction id for a client's ``tid`` (remapped when shared)."""
        if not self.remap:
            return tid
        pending, late = self.pending, self.late
        for _ in range(0x10000):
            utid = self.next_tid
            self.next_tid = (utid + 1) & 0xFFFF
            if utid not in pending and utid not in late:
                return utid
        return self.next_tid  # 65536 in flight: cannot happen with sane clients

    def _track(self, entry: Pending) -> None:
        """``entry`` is written upstream now: wait for its answer (its timer runs
        from when it was queued, or starts now)."""
        pending = self.pending
        lst = pending.get(entry.utid)
        if lst is None:
            pending[entry.utid] = [entry]
        else:
            lst.append(entry)
        if entry.deadline is None:
            self._start_timer(entry)
        else:  # queued while connecting: its timer runs already
            entry.client.outstanding.add(entry)

    def _start_timer(self, entry: Pending) -> None:
        """Count ``entry`` as its client's, on this link, and start its timeout."""
        entry.client.outstanding.add(entry)
        entry.link = self
        self.engine.arm(entry)

    @staticmethod
    def _cancel_timer(entry: Pending) -> None:
        entry.done = True

    def forget(self, entry: Pending, why: str | None = None) -> None:
        """Stop waiting for ``entry`` (its client left); a later answer is dropped."""
        self._cancel_timer(entry)
        if self.remove(entry) and why:
            self.remember_late(entry.utid, why)
        elif entry in self.queued:
            self.queued.remove(entry)

    def expire(self, entry: Pending) -> None:
        """No answer in time: 0x0B to the client, and nothing the upstream sends for
        it later may reach the client. Per client, the upstream connection is renewed
        (:meth:`_retire`): the old one drains and drops what it owes; shared, the id
        is remembered (ids are unique on the link) and a half-received answer resets
        the link. An answer whose first bytes the client has already (forwarded as
        they came) gets one more ``timeout``; then the client is dropped, since no
        exception can go between an answer's bytes."""
        engine = self.engine
        if entry in self.queued:  # still connecting after the whole timeout
            entry.done = True
            self.queued.remove(entry)
            engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
            return
        per_client = not self.remap and self.state == "up"
        if entry is self.streaming or (
            per_client
            and self.passthrough
            and self.received > self.consumed
            and entry in self.pending.get(entry.utid, ())
        ):
            held = self.received - self.consumed
            if not entry.extended:
                entry.extended = True
                engine.arm(entry)
                return
            entry.done = True
            entry.client.drop(
                f"upstream sent {held} bytes of an answer and nothing more for "
                f"{2 * engine.config.timeout:g} s (the client has them: no exception "
                "can follow)"
            )
            if entry is self.streaming:
                self.streaming = None
                self.reset("the answer being forwarded stopped half-way")
            return
        entry.done = True
        if not self.remove(entry):
            return
        holder = self._retire() if per_client else self
        holder.remember_late(entry.utid, "answered 0x0B already")
        if not entry.client.closed:
            renewed = "; upstream connection renewed" if per_client else ""
            entry.client.notice(
                f"no answer from upstream within {engine.config.timeout:g} s to tid "
                f"{entry.tid}: answered 0x0B{renewed}",
                {"tid": entry.tid, "fc": entry.fc, "unit": entry.unit},
            )
        engine.answer_exception(entry, GATEWAY_TARGET_FAILED)
        if self.state == "retired":
            self.drained()
        elif (
            self.state == "up"
            and self.remap
            and self.streaming is None  # one being forwarded has a timer of its own
            and self.received > self.consumed
        ):
            self.reset(
                f"upstream sent an incomplete answer ({self.received - self.consumed} bytes) "
                "and nothing more"
            )

    def _retire(self) -> TcpLink:
        """Move this client's upstream connection aside after a gateway timeout: it
        takes no new requests, its requests in flight still get their answers (or
        their own 0x0B), anything else it receives is dropped and logged, and it
        closes once it owes nothing (:data:`LINGER`). New
        requests go on a new connection (opened now), so a late answer can never
        be taken for the answer to a request that reuses its transaction id."""
        old = TcpLink(self.engine, self.owner)
        old.state = "retired"
        old.parent = self
        old.proto, old.decoder, old.pending = self.proto, self.decoder, self.pending
        old.received, old.consumed = self.received, self.consumed
        if old.proto is not None:
            old.proto.link = old
        for lst in old.pending.values():
            for entry in lst:
                entry.link = old
        self.retired.append(old)
        while len(self.retired) > MAX_RETIRED:
            self.retired[0].close()
        self.proto = None
        self.decoder = None
        self.pending = {}
        self.late = OrderedDict()
        self.received = self.consumed = 0
        self.state = "down"
        self.next_attempt = 0.0
        self.engine.stats.upstream_renewed += 1
        old._linger()
        self.connect()
        return old

    def _linger(self) -> None:
        """A retired connection waits for what it owes, then closes (:data:`LINGER`)."""
        self.engine.loop.call_later(LINGER * self.engine.config.timeout, self._linger_over)

    def _linger_over(self) -> None:
        if self.state != "retired":
            return
        if self.pending:
            self._linger()  # its own requests in flight expire (0x0B) first
            return
        self.close()

    def connection_lost(self, proto: UpstreamSocket, exc: Exception | None) -> None:
        if proto is not self.proto:
            return
        self.proto = None
        self.decoder = None
        if self.state == "closed":
            return
        if self.state == "retired":
            self._detach()
            in_flight = [e for lst in self.pending.values() for e in lst]
            self.pending = {}
            if in_flight:
                self.notice(
                    f"upstream {self.engine.config.upstream} closed a renewed connection "
                    f"with {len(in_flight)} requests in flight: answered 0x0B",
                    {"upstream": self.engine.config.upstream},
                )
            for entry in in_flight:
                self._cancel_timer(entry)
                self.engine.answer_exception(entry, GATEWAY_TARGET_FAILED)
            return
        self.state = "down"
        self.next_attempt = 0.0  # a lost connection is tried again at once
        how = "rst" if exc is not None or self.resetting else "fin"
        by = "proxy" if self.resetting else "upstream"
        if by == "upstream":
            self.engine.upstream_state = f"lost ({how.upper()})"
        self.resetting = False
        # a client that has part of an answer already cannot be given an exception
        # after it: its stream cannot go on
        half = self.streaming.client if self.streaming is not None else None
        owner = self.owner
        if half is None and owner is not None and (self.received > self.consumed or owner.midway):
            half = owner
        held = self.received - self.consumed
        self.streaming = None
        self.tail = b""
        if half is not None:
            half.drop(
                f"the upstream connection ended after {held} bytes of an answer "
                "the client has already"
            )
        in_flight = [e for lst in self.pending.values() for e in lst]
        self.pending = {}
        if self.owner is None or not self.owner.closed:
            who = "the proxy reset" if by == "proxy" else "closed"
            self.notice(
                f"upstream {self.engine.config.upstream} {who} the connection "
                f"({how.upper()}{': ' + connection_error(exc) if exc else ''})"
                + (f"; {len(in_flight)} requests in flight answered 0x0B" if in_flight else ""),
                {"upstream": self.engine.config.upstream, "how": how, "by": by},
            )
        for entry in in_flight:
            self._cancel_timer(entry)
            self.remember_late(entry.utid, "the upstream connection was lost")
            self.engine.answer_exception(entry, GATEWAY_TARGET_FAILED)

    def write(self, data: bytes) -> None:
        proto = self.proto
        if proto is not None and proto.transport is not None:
            proto.transport.write(data)

    def _detach(self) -> None:
        """A retired connection ends: closed, and off its client's list."""
        self.state = "closed"
        parent = self.parent
        if parent is not None and self in parent.retired:
            parent.retired.remove(self)

    def close(self) -> None:
        """The owner is gone (or a retired connection is done): no reconnects, and
        the connection closes."""
        self._detach()
        for old in list(self.retired):
            old.close()
        for lst in self.pending.values():
            for entry in lst:
                self._cancel_timer(entry)
        for entry in self.queued:
            self._cancel_timer(entry)
        self.pending = {}
        self.queued = []
        proto = self.proto
        if proto is not None and proto.transport is not None:
            proto.transport.close()
