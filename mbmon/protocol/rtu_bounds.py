"""Where the RTU bus draws frame boundaries: the line-up heuristics of :mod:`mbmon.protocol.rtu`.

:class:`~mbmon.protocol.rtu.RtuDecoder` frames by length prediction and CRC;
when a reading cannot be decided from its own bytes (its length needs bytes
still to come, it has no predictable length, or its CRC fails) the decoder
asks a :class:`RtuBounds` it owns what the bytes around it say:

* a *frame of its own* is a frame of predictable length with a valid CRC
  (``RtuBounds._standalone``); frames of their own *line up with the bus*
  when one starts or ends at the latest silence, ends the bytes before a
  silence or the stream, or is followed by another (:meth:`RtuBounds.lines_up`,
  which also counts frames found by a CRC scan at the silence);
* a CRC that validates at a boundary the bus marks is a frame whatever its
  fields say (:meth:`RtuBounds.boundary`), unless the bytes may be one frame
  going on across a silence (:meth:`RtuBounds.may_go_on`);
* a CRC match found by scanning is refused when it swallows frames of their
  own (:meth:`RtuBounds.crosses_frames`).

This module also holds what both modules share: the ADU size rules, the size
limits, the modes of a decoding pass and the CRC scan. The rules of the RTU
decoder's module docstring say when each heuristic applies.

Pure: no I/O, no clocks.
"""

from __future__ import annotations

from mbmon.protocol.crc import CRC_TABLE
from mbmon.protocol.crc import crc_ok_at as _crc_ok
from mbmon.protocol.functions import derived
from mbmon.protocol.pdu import NEED_MORE, pdu_length, simple_length_rules

__all__ = [
    "FINAL",
    "MAX_ADU",
    "MIN_ADU",
    "PEEK",
    "REQ_RULES",
    "RESP_RULES",
    "SILENCE",
    "STREAM",
    "RtuBounds",
    "scan_crc",
]


def _adu_rules(response: bool) -> dict[int, int | tuple[int, int]]:
    """``simple_length_rules`` as ADU sizes: fixed ADU length, or ``(i, base)``
    with the ADU ``base + adu[i]`` long (unit id and CRC counted in)."""
    return {
        fc: rule + 3 if isinstance(rule, int) else (rule[0] + 1, rule[1] + 3)
        for fc, rule in simple_length_rules(response).items()
    }


REQ_RULES: dict[int, int | tuple[int, int]] = {}
"""ADU sizes of requests by function code (see :func:`_adu_rules`); kept up to date in place."""

RESP_RULES: dict[int, int | tuple[int, int]] = {}
"""ADU sizes of responses by function code, like :data:`REQ_RULES`."""


@derived
def _rules_from_table() -> None:
    """Fill the ADU rules in place, again when a function code is registered."""
    for rules, response in ((REQ_RULES, False), (RESP_RULES, True)):
        rules.clear()
        rules.update(_adu_rules(response))


MAX_ADU = 256
"""Largest RTU ADU: unit id + 253-byte PDU + CRC (spec limit); also the scan limit."""

MIN_ADU = 4
"""Smallest RTU ADU: unit id + function code + CRC."""

PEEK = 16
"""Bytes handed to ``pdu_length`` first; every fixed rule reads at most index 9."""

# Modes of one decoding pass.
STREAM = 0
"""Mode of a decoding pass: more bytes will come, wait whenever a decision needs them."""
SILENCE = 1
"""Mode of a decoding pass: a silence follows; settle noise, wait for predicted lengths
and open scans."""
FINAL = 2
"""Mode of a decoding pass: end of stream, decide everything with the bytes present."""


def scan_crc(buf: bytes | bytearray, start: int, limit: int) -> int:
    """Shortest length L in MIN_ADU..limit with a valid CRC at ``buf[start:start+L]``, else 0."""
    table = CRC_TABLE
    crc = 0xFFFF
    crc = (crc >> 8) ^ table[(crc ^ buf[start]) & 0xFF]
    crc = (crc >> 8) ^ table[(crc ^ buf[start + 1]) & 0xFF]
    for length in range(MIN_ADU, limit + 1):
        i = start + length - 2
        lo = buf[i]
        if lo == (crc & 0xFF) and buf[i + 1] == (crc >> 8):
            return length
        crc = (crc >> 8) ^ table[(crc ^ lo) & 0xFF]
    return 0


def _no_frame(buf: bytes | bytearray, start: int, end: int) -> bool:
    """Whether the CRC-valid ADU ``buf[start:end]`` can be no frame: function code 0
    or 0x80 (the decoder never frames them), or an exception answer that is none
    (an exception answer is 5 bytes with an exception code from 1 up). Such a
    match is no frame lining up with the bus, only a CRC that matched by chance
    or by design (``FF FF`` is the CRC of nothing: ``FF FF 00 00``, ``FF FF 00 00
    00`` and every longer run of zeros after it pass), so it never cuts short a
    frame still coming in. (A frame whose fields disagree with its length is
    otherwise taken at a boundary the bus marks: libmodbus's quantity-0 writes;
    exception answers come from the slave's stack, whole.)"""
    fc = buf[start + 1]
    if fc & 0x80:
        return fc == 0x80 or end - start != 5 or not buf[start + 2]
    return not fc


class RtuBounds:
    """The line-up heuristics of one :class:`~mbmon.protocol.rtu.RtuDecoder`.

    Owns what they read of the bus: the readings allowed (``allow_req``,
    ``allow_resp``: fixed by the decoder's direction), ``mark`` (bytes of the
    decoder's buffer that came before the latest silence; the decoder moves
    it), ``bursty`` (a frame went on across a silence, so silences may be a USB
    adapter's latency; the decoder sets it) and the memos of one decoding pass,
    which :meth:`new_pass` clears. ``buf[:n]`` is the decoder's bytes and
    ``mode`` the pass's mode (:data:`STREAM`, :data:`SILENCE`, :data:`FINAL`)
    in every method.
    """

    __slots__ = (
        "_at_mark",
        "_in_scan",
        "_lined",
        "_near",
        "_tails",
        "allow_req",
        "allow_resp",
        "bursty",
        "mark",
    )

    def __init__(self, allow_req: bool, allow_resp: bool) -> None:
        self.allow_req = allow_req
        self.allow_resp = allow_resp
        self.mark = 0  # bytes of the decoder's buffer that came before the latest silence
        #: a frame went on across a silence: silences may be a USB adapter's latency
        self.bursty = False
        #: within one decoding pass: (lo, k, s), no frame of its own starts in (lo, k),
        #: at k one of length s (-1: cannot tell yet; 0: k is where the search stopped)
        self._near: tuple[int, int, int] | None = None
        #: within one decoding pass: (lo, first, k, state, fits), for offsets lo..first-1
        #: (first: the next frame of its own) frames line up with the bus at k
        #: (state 1), cannot be told at k (-1), or do not before k (0), with ``fits``
        self._lined: tuple[int, int, int, int, bool] | None = None
        self._tails: list[int] | None = None  # within one pass: see _ends_at_silence
        self._at_mark: int | None = None  # within one pass: see _scanned_at_mark
        self._in_scan: tuple[int, int, bool] | None = None  # within one pass: see _scanned_within

    def new_pass(self) -> None:
        """A decoding pass starts (the buffer or its offsets changed): forget the memos."""
        self._near = self._lined = self._tails = self._at_mark = self._in_scan = None

    def lines_up(
        self,
        buf: bytes | bytearray,
        pos: int,
        n: int,
        mode: int,
        far: int,
        within: bool = True,
        fits: bool = False,
    ) -> bool:
        """Whether frames after ``pos`` and before ``far`` line up with the bus: of
        their own (:meth:`_lined_up`) or found by a scan (:meth:`_scanned`).

        A CRC match that can be no frame (:func:`_no_frame`) never counts. One
        lying whole before a silence, ending at no boundary the bus marked,
        counts only with ``within``; with ``fits`` (the bytes at ``pos`` read as
        the answer the pending request awaits) a match that is no frame of its
        own counts only when its fields agree with its length (:meth:`_fits`).
        """
        return self._lined_up(buf, pos, n, mode, far, fits) == 1 or self._scanned(
            buf, pos, n, mode, far, within, fits
        )

    def _counts(self, buf: bytes | bytearray, start: int, end: int, fits: bool) -> bool:
        """Whether the CRC match ``buf[start:end]`` (no frame of its own) counts as a
        frame lining up with the bus: never when it can be no frame, with ``fits``
        only when its fields agree with its length."""
        if fits:
            return self._fits(buf, start, end)
        return not _no_frame(buf, start, end)

    def _next_frame(self, buf: bytes | bytearray, pos: int, n: int, mode: int) -> tuple[int, int]:
        """The first offset ``k`` after ``pos`` (at most ``MAX_ADU`` on) where a frame
        of predictable length with a valid CRC starts: ``(k, its length)``, or
        ``(where the search stopped, 0)`` when there is none. An offset whose
        frame would need bytes still to come is passed over: such a frame
        would run past the frames found after it, and they frame on their own.
        Remembered within one decoding pass, so a run of noise costs one look
        at each offset."""
        stop = min(n, pos + MAX_ADU + 1)
        start = pos + 1
        near = self._near
        if near is not None and near[0] <= pos < near[1]:
            if near[2]:
                return near[1], near[2]
            start = near[1]
            lo = near[0]
        else:
            lo = pos
        k = start
        found = 0
        while k < stop:
            found = self._standalone(buf, k, n, mode)
            if found > 0:
                break
            k += 1
        else:
            found = 0
        self._near = (lo, k, found)
        return k, found

    def _lined_up(
        self, buf: bytes | bytearray, pos: int, n: int, mode: int, far: int, fits: bool = False
    ) -> int:
        """Whether frames of their own after ``pos`` and before ``far`` line up with the
        bus: one starts or ends at the latest silence, ends the bytes before a
        silence or the stream, or is followed by another (right after it or
        later: two CRCs a guess would swallow); at a silence on a line not
        bursty, a CRC that validates right at the silence lines up too (one
        that counts: :meth:`_counts`). 1 yes, 0 no, -1 cannot tell yet.
        Remembered within one decoding pass (``_lined``, for one value of
        ``fits``) like :meth:`_next_frame`."""
        lined = self._lined
        if lined is not None and lined[0] <= pos < lined[1] and lined[4] == fits:
            k, state = lined[2], lined[3]
            if state:
                return state if k < far else 0
            if far <= k:
                return 0
        k, length = self._next_frame(buf, pos, n, mode)
        first = k
        mark = self.mark
        stop = min(far, n)
        state = 0
        seen = False
        unsure = -1  # where a frame's follower could not be told yet (bytes to come)
        while length and k < stop:
            end = k + length
            if (
                seen
                or (mark and (k == mark or end == mark))
                or (mode != STREAM and end == n)
                or (not self.bursty and (mode == SILENCE or end <= mark))
            ):
                state = 1
                break
            after = self._standalone(buf, end, n, mode)
            if after > 0:
                state = 1
                break
            if after and unsure < 0:
                # a follower cannot be told yet, but a later frame (at the silence,
                # or a second one) may line up for sure: look on
                unsure = k
            seen = True
            k += 1
            length = 0
            while k < stop:
                length = self._standalone(buf, k, n, mode)
                if length > 0:
                    break
                length = 0
                k += 1
        else:
            k = stop
            if mode == SILENCE and not self.bursty:
                # a frame whose fields disagree ends at the silence: its CRC there
                # lines it up as well (what follows is settled by the silence)
                for j in self._ends_at_silence(buf, n):
                    if pos < j < stop and self._counts(buf, j, n, fits):
                        k, state = j, 1
                        break
        if not state and unsure >= 0:
            k, state = unsure, -1
        self._lined = (pos, first, k, state, fits)
        return state if k < far else 0

    def _ends_at_silence(self, buf: bytes | bytearray, n: int) -> list[int]:
        """Offsets ``j`` (ascending, the last ``MAX_ADU`` bytes) where a CRC-valid ADU
        ``buf[j:n]`` ends right at the silence; computed once per decoding pass."""
        tails = self._tails
        if tails is None:
            tails = [j for j in range(max(0, n - MAX_ADU), n - MIN_ADU + 1) if _crc_ok(buf, j, n)]
            self._tails = tails
        return tails

    def boundary(self, buf: bytes | bytearray, pos: int, n: int, mode: int) -> int:
        """Length of a CRC-valid ADU at ``pos`` that ends at a boundary the bus marks:
        the latest silence, the end of the bytes before a silence (or of the
        stream), or where the next frame of its own starts; never past that
        frame. 0 none, -1 cannot tell yet (no boundary in sight, more bytes to come)."""
        k, length = self._next_frame(buf, pos, n, mode)
        mark = self.mark
        ends = [k] if length else []
        if pos < mark <= k:
            ends.append(mark)
        if mode != STREAM and n <= k:
            ends.append(n)
        for end in sorted(ends):
            if end - pos >= MIN_ADU and _crc_ok(buf, pos, end):
                return end - pos
        if not length and mode == STREAM and k >= n:
            # a frame found by a scan right at the silence is a boundary in sight
            return 0 if self._scanned_at_mark(buf, pos, n, n) else -1
        return 0

    def _scanned(
        self,
        buf: bytes | bytearray,
        pos: int,
        n: int,
        mode: int,
        far: int,
        within: bool = True,
        fits: bool = False,
    ) -> bool:
        """Whether a frame found by a CRC scan (any function code; one that counts:
        :meth:`_counts`) after ``pos`` and before ``far`` says the bytes at ``pos``
        are no frame going on: one starts right at the latest silence
        (:meth:`_scanned_at_mark`), or, with ``within``, at a silence on a line
        whose silences have been real so far (not bursty), one lies whole in the
        bytes before it (:meth:`_scanned_within`)."""
        if self._scanned_at_mark(buf, pos, n, far, fits):
            return True
        return (
            within
            and mode == SILENCE
            and not self.bursty
            and 0 < self._scanned_within(buf, pos, n, fits) < far
        )

    def _scanned_within(self, buf: bytes | bytearray, pos: int, n: int, fits: bool = False) -> int:
        """The first offset after ``pos`` where a CRC scan finds an ADU that ends by
        ``n`` and counts (:meth:`_counts`), or 0. Remembered within one decoding
        pass (``_in_scan``: offsets ``lo..k-1`` have none before ``k``, for one
        value of ``fits``), so a run of noise scans each offset once."""
        memo = self._in_scan
        if memo is not None and memo[0] <= pos < memo[1] and memo[2] == fits:
            return memo[1] if memo[1] < n else 0
        j = pos + 1
        while j <= n - MIN_ADU:
            found = scan_crc(buf, j, min(MAX_ADU, n - j))
            if found and self._counts(buf, j, j + found, fits):
                break
            j += 1
        if j > n - MIN_ADU:
            j = n
        self._in_scan = (pos, j, fits)
        return j if j < n else 0

    def _scanned_at_mark(
        self, buf: bytes | bytearray, pos: int, n: int, far: int, fits: bool = False
    ) -> bool:
        """Whether a CRC-valid ADU (found by a scan: any function code; one that
        counts: :meth:`_counts`) starts right at the latest silence, after ``pos``
        and before ``far``: a frame starts at a
        silence, so the bytes before it are no frame going on across it. The scan
        is done once per decoding pass."""
        mark = self.mark
        if not pos < mark < far or mark > n - MIN_ADU:
            return False
        found = self._at_mark
        if found is None:
            found = self._at_mark = scan_crc(buf, mark, min(MAX_ADU, n - mark))
        return found > 0 and self._counts(buf, mark, mark + found, fits)

    def may_go_on(self, buf: bytes | bytearray, pos: int, n: int, mode: int) -> bool:
        """At a silence, whether the bytes from ``pos`` whose readings failed may be
        one frame going on after it: nothing of its own starts after ``pos``, no
        CRC validates at the silence from a later offset, no frame found by a
        scan says otherwise (:meth:`_scanned`), and fewer than ``MAX_ADU`` bytes
        are there. A USB adapter's latency looks like a
        silence, and a frame whose fields disagree with its length (its CRC at its
        true end) can be cut there; its CRC at a boundary the next bytes mark then
        decides it. Noise held so is reported with those bytes, or at the end of
        the stream (``silence``); it never holds back a frame after it."""
        if mode != SILENCE or n - pos >= MAX_ADU or self._next_frame(buf, pos, n, mode)[1]:
            return False
        if self._scanned(buf, pos, n, mode, n):
            return False
        # a CRC that validates right at the silence after pos marks a frame there
        return not any(j > pos for j in self._ends_at_silence(buf, n))

    def crosses_frames(
        self, buf: bytes | bytearray, start: int, end: int, n: int, mode: int
    ) -> int:
        """Whether the scanned candidate ``buf[start:end]`` swallows frames: 1 yes, 0 no,
        -1 cannot tell yet (bytes missing while more will come).

        Yes when a frame of predictable length with a valid CRC starts inside it
        and either reaches ``end`` (or beyond) or is followed right away by a
        second such frame. Offsets before the latest silence are told as at the
        silence (as :meth:`frame_within` does): a frame there that needs more
        bytes than all those present is none, not a reason to wait.
        """
        mark = self.mark if mode == STREAM else 0
        for j in range(start + 1, end):
            first = self._standalone(buf, j, n, SILENCE if j < mark else mode)
            if first < 0:
                return -1
            if not first:
                continue
            if j + first >= end:
                return 1
            second = self._standalone(buf, j + first, n, SILENCE if j + first < mark else mode)
            if second < 0:
                return -1
            if second:
                return 1
        return 0

    def frame_within(self, buf: bytes | bytearray, start: int, mark: int, n: int, mode: int) -> int:
        """Whether a frame of predictable length with a valid CRC starts in
        ``buf[start:mark + 1]`` (at the silence ``mark`` at the latest): 1 yes,
        0 no, -1 the one at ``mark`` cannot be told yet."""
        for j in range(start, min(mark, n - 1) + 1):
            found = self._standalone(buf, j, n, mode if j == mark else SILENCE)
            if found:
                return 1 if found > 0 else -1
        return 0

    def _fits(self, buf: bytes | bytearray, start: int, end: int) -> bool:
        """Whether the CRC-valid ADU ``buf[start:end]`` is a frame whose fields agree
        with its length under a reading the decoder allows: one whose function
        code predicts exactly ``end - start`` bytes; never one that can be no
        frame, nor one of no predictable length (a 4-byte run "unit, unknown
        code, CRC" matches by chance far more often than an answer is cut)."""
        if _no_frame(buf, start, end):
            return False
        fc = buf[start + 1]
        pdu = buf[start + 1 : end - 2]
        for is_resp in (False, True):
            if not (self.allow_resp if is_resp else self.allow_req) or (fc & 0x80 and not is_resp):
                continue
            if pdu_length(pdu, is_resp) == len(pdu):
                return True
        return False

    def _standalone(self, buf: bytes | bytearray, k: int, n: int, mode: int) -> int:
        """Length of a frame of predictable length with a valid CRC at ``k``, 0 when
        there is none, -1 when the bytes to tell are still missing (``STREAM``)."""
        avail = n - k
        if avail < 2:
            return -1 if mode == STREAM else 0
        fc = buf[k + 1]
        if fc == 0 or fc == 0x80:
            return 0
        if fc & 0x80 and avail > 2 and not buf[k + 2]:
            return 0  # exception code 0: see _no_frame
        short = False
        for is_resp in (False, True):
            if not (self.allow_resp if is_resp else self.allow_req):
                continue
            if fc & 0x80 and not is_resp:
                continue
            rule = (RESP_RULES if is_resp else REQ_RULES).get(fc)
            if isinstance(rule, int):  # the simple rules as the framing loop reads them
                total = rule
            elif rule is not None:
                at = k + rule[0]
                if at >= n:
                    short = True
                    continue
                total = rule[1] + buf[at]
            else:
                plen = pdu_length(buf[k + 1 : k + 1 + PEEK], is_resp)
                if plen == NEED_MORE and avail - 1 > PEEK:
                    plen = pdu_length(buf[k + 1 : k + MAX_ADU], is_resp)
                if plen is None:
                    continue
                if plen == NEED_MORE:
                    short = True
                    continue
                if plen < 1:
                    continue
                total = plen + 3
            if total > MAX_ADU:
                continue
            if total > avail:
                short = True
            elif _crc_ok(buf, k, k + total):
                return total
        return -1 if short and mode == STREAM else 0
