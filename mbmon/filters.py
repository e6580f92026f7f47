"""Record filters (``--unit``, ``--fc``, ``--address``, ``--grep``, ``--since``/``--until``)
and the replay pace, for every command that selects records.

Owns one implementation of the filters for both kinds of record a command
sees: live :class:`~mbmon.model.Record` objects (``read``:
:meth:`RecordFilter.matches_record`) and logged ``read --json`` objects
(``replay``/``export``: :meth:`RecordFilter.matches`), the parsing of their
values (:func:`parse_fcs`, :func:`parse_range`, times by
:func:`mbmon.timefmt.parse_when`), the options themselves
(:func:`add_filter_options`, :func:`build_filter`) and :class:`Pacer`, the
``--speed`` schedule (one monotonic start, no drift), and the one expression
grammar (:func:`parse_expression`) that both the display filter (``--where``)
and the capture triggers (``--trigger``, :mod:`mbmon.analysis.trigger`) read.
"""

from __future__ import annotations

import argparse
import operator
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from mbmon.model import Kind, Record
from mbmon.timefmt import TimeFormat, TimeParseError
from mbmon.timefmt import parse_when as _parse_time

__all__ = [
    "EXPRESSION_HELP",
    "Expression",
    "FilterError",
    "Pacer",
    "RecordFilter",
    "add_filter_options",
    "build_filter",
    "iter_filtered",
    "parse_expression",
    "parse_fcs",
    "parse_int",
    "parse_range",
    "parse_when",
    "touches",
]


class FilterError(ValueError):
    """A filter value that cannot be understood (a usage error)."""


def parse_when(text: str, start: float | None, fmt: TimeFormat | None = None) -> float:
    """A ``--since``/``--until`` value as epoch seconds (every form ``-t`` prints;
    see :func:`mbmon.timefmt.parse_when`); :class:`FilterError` when it is none."""
    try:
        return _parse_time(text, start, fmt)
    except TimeParseError as exc:
        raise FilterError(str(exc)) from None


def parse_int(text: str) -> int:
    try:
        return int(text.strip(), 0)
    except ValueError:
        raise FilterError(f"not a number: {text!r}") from None


def parse_units(texts: Iterable[str]) -> frozenset[int]:
    """``--unit 1,2 --unit 3`` -> {1, 2, 3}; unit ids are 0..255."""
    out = frozenset(parse_int(p) for value in texts for p in value.split(",") if p.strip())
    if not out or any(not 0 <= unit <= 0xFF for unit in out):
        raise FilterError(f"unit ids are 0..255: {','.join(texts)!r}")
    return out


def parse_fcs(text: str) -> frozenset[int]:
    """``--fc 3,0x10`` -> {3, 16}."""
    out = {parse_int(part) for part in text.split(",") if part.strip()}
    if not out or any(not 0 <= fc <= 0xFF for fc in out):
        raise FilterError(f"function codes are 1..127: {text!r}")
    return frozenset(fc & 0x7F for fc in out)


def parse_range(text: str) -> tuple[int, int]:
    """``--address 200`` or ``200-251`` (inclusive; 0x.. accepted)."""
    first, dash, last = text.partition("-")
    lo = parse_int(first)
    hi = parse_int(last) if dash else lo
    if lo > hi or lo < 0 or hi > 0xFFFF:
        raise FilterError(f"not an address range A[-B] within 0..65535: {text!r}")
    return lo, hi


def _meets(address: Any, count: Any, fields: Any, lo: int, hi: int) -> bool:
    """Whether a register/coil range (``address``, ``count``) or a 0x17 write range
    (``fields``) meets [lo, hi]."""
    if isinstance(address, int):
        n = count if isinstance(count, int) and count > 0 else 1
        if address <= hi and address + n - 1 >= lo:
            return True
    if isinstance(fields, Mapping) and isinstance(fields.get("write_address"), int):
        wa = fields["write_address"]
        wc = fields.get("write_count")
        if wa <= hi and wa + (wc if isinstance(wc, int) and wc > 0 else 1) - 1 >= lo:
            return True
    return False


def touches(obj: Mapping[str, Any], lo: int, hi: int) -> bool:
    """Whether a logged frame's register/coil range (or 0x17's write range) meets [lo, hi]."""
    return _meets(obj.get("address"), obj.get("count"), obj.get("fields"), lo, hi)


@dataclass(slots=True)
class RecordFilter:
    """The record filters; an unset filter lets everything through.

    Frame filters (unit, function code, address) let only records that have
    those fields through: events pass only when no frame filter is set.
    ``since``/``until`` are epoch seconds, inclusive. When the first record's
    time was not known as the filter was built (``read``: a capture being
    read), ``since_text``/``until_text`` hold the values and are resolved
    against the first record seen (:meth:`start_at`).
    """

    units: frozenset[int] | None = None
    fcs: frozenset[int] | None = None
    address: tuple[int, int] | None = None
    since: float | None = None
    until: float | None = None
    grep: str | None = None
    since_text: str | None = None
    until_text: str | None = None
    time_format: TimeFormat | None = None
    where: Expression | None = None

    @property
    def active(self) -> bool:
        return any(
            v is not None
            for v in (
                self.units, self.fcs, self.address, self.since, self.until, self.grep,
                self.since_text, self.until_text, self.where,
            )
        )  # fmt: skip

    @property
    def frame_filters(self) -> bool:
        """Whether a frame filter (unit, function code, address) is set."""
        return self.units is not None or self.fcs is not None or self.address is not None

    @property
    def needs_line(self) -> bool:
        """Whether :meth:`matches_record` needs the record's text line (``--grep``)."""
        return self.grep is not None

    def start_at(self, start: float) -> None:
        """Resolve ``--since``/``--until`` texts against the first record's time."""
        if self.since_text is not None:
            self.since = parse_when(self.since_text, start, self.time_format)
            self.since_text = None
        if self.until_text is not None:
            self.until = parse_when(self.until_text, start, self.time_format)
            self.until_text = None

    def _time_ok(self, ts: float) -> bool:
        if self.since_text is not None or self.until_text is not None:
            self.start_at(ts)
        if self.since is not None and not ts >= self.since:
            return False
        return self.until is None or ts <= self.until

    def matches(self, obj: Mapping[str, Any] | None, line: str, ts: float) -> bool:
        """Whether a logged record (its ``read --json`` object, line and time) passes."""
        if not self._time_ok(ts):
            return False
        if self.grep is not None and self.grep.lower() not in line.lower():
            return False
        if self.where is not None and (obj is None or not self.where.matches(obj)):
            return False
        if self.units is None and self.fcs is None and self.address is None:
            return True
        if obj is None:
            return False
        if self.units is not None and obj.get("unit") not in self.units:
            return False
        if self.fcs is not None and obj.get("fc") not in self.fcs:
            return False
        return self.address is None or touches(obj, *self.address)

    def matches_record(self, record: Record, line: str | None = None) -> bool:
        """Whether a live record passes; ``line`` is its text line (needed for
        ``--grep`` only: see :attr:`needs_line`). Records of a stream without
        capture times (a raw RTU dump) ignore ``--since``/``--until``."""
        stream = record.stream
        if (stream is None or stream.timed) and not self._time_ok(record.ts):
            return False
        if self.grep is not None:
            if line is None:
                raise ValueError("--grep needs the record's line")
            if self.grep.lower() not in line.lower():
                return False
        if self.where is not None and not self.where.matches_record(record):
            return False
        if self.units is None and self.fcs is None and self.address is None:
            return True
        frame = record.frame
        if frame is None:
            return False
        pdu = frame.pdu
        if self.units is not None and frame.unit not in self.units:
            return False
        if self.fcs is not None and pdu.fc not in self.fcs:
            return False
        if self.address is None:
            return True
        address, count = pdu.address, pdu.count
        request = record.request
        if address is None and request is not None and pdu.kind is not Kind.REQUEST:
            address, count = request.pdu.address, request.pdu.count  # as the JSON record
        return _meets(address, count, pdu.fields, *self.address)


def iter_filtered(records: Iterable[Any], flt: RecordFilter) -> Iterator[Any]:
    """The logged records (``obj``, ``text``, ``time``) that pass ``flt``."""
    for rec in records:
        if flt.matches(rec.obj, rec.text, rec.time):
            yield rec


# --------------------------------------------------------------------------- options

TIMES_HELP = (
    "times: +5s / +1m30s / +250ms / 2.5 from the first record, 12:00:05.123456 (time of "
    "day on the first record's day), 2024-05-01 12:00:05 (ISO 8601, local time unless it "
    "says otherwise; with -t u/ud: UTC), or epoch seconds: every form -t prints. --since "
    "and --until are inclusive."
)


def add_filter_options(parser: argparse.ArgumentParser) -> None:
    """Add the filter options (a group ``filters``) to a command: ``--unit``, ``--fc``,
    ``--address``, ``--since``, ``--until``, ``--grep``; :func:`build_filter` reads them."""
    group = parser.add_argument_group("filters")
    group.add_argument(
        "--unit", action="append", metavar="N", help="only this unit id (N[,N], repeatable)"
    )
    group.add_argument(
        "--fc", action="append", metavar="N[,N]", help="only these function codes (3,0x10)"
    )
    group.add_argument(
        "--address",
        metavar="A[-B]",
        help="only requests/responses touching register or coil addresses A..B",
    )
    group.add_argument("--since", metavar="TIME", help="from TIME on (see 'times' below)")
    group.add_argument("--until", metavar="TIME", help="up to TIME")
    group.add_argument("--grep", metavar="TEXT", help="only lines containing TEXT (any case)")
    group.add_argument(
        "--where",
        metavar="EXPR",
        help="only records EXPR matches, e.g. 'exception or latency > 50ms', "
        "'fc 6 and address 200', 'R200 != 0' (the grammar of --trigger; docs/usage.md)",
    )


def build_filter(
    args: argparse.Namespace,
    start: float | None = None,
    time_format: TimeFormat | None = None,
    *,
    start_known: bool = True,
) -> RecordFilter:
    """The filter the options of :func:`add_filter_options` ask for.

    ``start`` is the first record's time (a log knows it); with
    ``start_known=False`` (a capture not read yet) ``--since``/``--until`` are
    checked now and resolved at the first record. ``time_format`` is the
    output's (``-t``): with ``u``/``ud`` times without a zone are UTC.
    Raises :class:`FilterError` for a value that cannot be understood.
    """
    flt = RecordFilter(time_format=time_format)
    if getattr(args, "unit", None):
        flt.units = parse_units(args.unit)
    if getattr(args, "fc", None):
        flt.fcs = frozenset().union(*(parse_fcs(v) for v in args.fc))
    if getattr(args, "address", None):
        flt.address = parse_range(args.address)
    since, until = getattr(args, "since", None), getattr(args, "until", None)
    for text in (since, until):
        if text:
            parse_when(text, 0.0, time_format)  # a usage error now, not at the first record
    if start_known:
        if since:
            flt.since = parse_when(since, start, time_format)
        if until:
            flt.until = parse_when(until, start, time_format)
    else:
        flt.since_text = since or None
        flt.until_text = until or None
    if getattr(args, "grep", None):
        flt.grep = args.grep
    if getattr(args, "where", None):
        flt.where = parse_expression(args.where)
    return flt


# --------------------------------------------------------------------------- expressions

EXPRESSION_HELP = (
    "expressions (--where, --trigger): tests joined by 'and', 'or', 'not' and "
    "parentheses. Tests: exception [CODE], timeout, noise, crc, connect, disconnect, "
    "gap, guard, request, response, fc N[,N], unit N[,N], address A[-B], latency OP "
    "TIME (latency > 50ms), and a value a frame carries: R|IR|C|DI<address> OP N "
    "(R200 != 0: holding register 200; IR input register, C coil, DI discrete "
    "input). OP is one of == != < <= > >=."
)

_TOKEN = re.compile(r"\s*(==|!=|<=|>=|<|>|\(|\)|[^\s()<>=!]+)")
_COMPARE: dict[str, Callable[[Any, Any], bool]] = {
    "==": operator.eq, "!=": operator.ne, "<": operator.lt, "<=": operator.le,
    ">": operator.gt, ">=": operator.ge,
}  # fmt: skip
_ITEM = re.compile(r"^(R|HR|IR|C|DI)(\d+)$", re.IGNORECASE)
_TABLES = {"R": "holding_register", "HR": "holding_register", "IR": "input_register",
           "C": "coil", "DI": "discrete_input"}  # fmt: skip
_EVENTS = frozenset({"timeout", "connect", "disconnect", "gap", "guard"})
_KINDS = frozenset({"request", "response", "noise"})

# A test is a function of a record's ``read --json`` object.
_Test = Callable[[Mapping[str, Any]], bool]


class Expression:
    """A parsed expression (:func:`parse_expression`): ``matches(obj)`` for a
    logged record's ``read --json`` object, ``matches_record(record)`` for a
    live record (through the same object: one meaning for both)."""

    __slots__ = ("_test", "text")

    def __init__(self, text: str, test: _Test) -> None:
        self.text = text
        self._test = test

    def matches(self, obj: Mapping[str, Any]) -> bool:
        """Whether a record's ``read --json`` object satisfies the expression."""
        return self._test(obj)

    def matches_record(self, record: Record) -> bool:
        """Whether a live record satisfies the expression."""
        global _AS_JSON
        if _AS_JSON is None:
            from mbmon.format import View, record_to_json

            view = View()
            _AS_JSON = lambda r: record_to_json(r, view, line=False)  # noqa: E731
        return self._test(_AS_JSON(record))

    def __repr__(self) -> str:
        return f"Expression({self.text!r})"


#: a record as its ``read --json`` object (made at first use: format is imported lazily)
_AS_JSON: Callable[[Record], Mapping[str, Any]] | None = None


def parse_expression(text: str) -> Expression:
    """Parse the grammar of :data:`EXPRESSION_HELP` (the display filter's and the
    triggers'); :class:`FilterError` names what is wrong and where."""
    tokens = _TOKEN.findall(text)
    if "".join(tokens) != re.sub(r"\s+", "", text):
        raise FilterError(f"cannot read the expression {text!r}")
    if not tokens:
        raise FilterError("empty expression")
    parser = _Parser(tokens, text)
    test = parser.parse_or()
    if parser.pos != len(tokens):
        raise FilterError(f"unexpected {tokens[parser.pos]!r} in {text!r}")
    return Expression(text, test)


class _Parser:
    """Recursive descent: or := and ('or' and)*; and := not ('and' not)*;
    not := 'not' not | '(' or ')' | test."""

    def __init__(self, tokens: list[str], text: str) -> None:
        self.tokens = tokens
        self.text = text
        self.pos = 0

    def peek(self) -> str | None:
        return self.tokens[self.pos] if self.pos < len(self.tokens) else None

    def take(self, what: str = "a test") -> str:
        token = self.peek()
        if token is None:
            raise FilterError(f"{what} expected at the end of {self.text!r}")
        self.pos += 1
        return token

    def parse_or(self) -> _Test:
        parts = [self.parse_and()]
        while (self.peek() or "").lower() == "or":
            self.pos += 1
            parts.append(self.parse_and())
        return parts[0] if len(parts) == 1 else (lambda o: any(p(o) for p in parts))

    def parse_and(self) -> _Test:
        parts = [self.parse_not()]
        while (self.peek() or "").lower() == "and":
            self.pos += 1
            parts.append(self.parse_not())
        return parts[0] if len(parts) == 1 else (lambda o: all(p(o) for p in parts))

    def parse_not(self) -> _Test:
        token = self.take()
        low = token.lower()
        if low == "not":
            inner = self.parse_not()
            return lambda o: not inner(o)
        if token == "(":
            inner = self.parse_or()
            if self.take("')'") != ")":
                raise FilterError(f"')' expected in {self.text!r}")
            return inner
        return self.parse_test(token)

    def number(self, what: str) -> int:
        token = self.take(what)
        try:
            return int(token, 0)
        except ValueError:
            raise FilterError(f"{what} expected, not {token!r}, in {self.text!r}") from None

    def compare(self) -> Callable[[Any, Any], bool]:
        token = self.take("a comparison (== != < <= > >=)")
        if token not in _COMPARE:
            raise FilterError(f"a comparison expected, not {token!r}, in {self.text!r}")
        return _COMPARE[token]

    def parse_test(self, token: str) -> _Test:
        low = token.lower()
        if low == "exception":
            nxt = self.peek()
            if nxt is not None and re.fullmatch(r"\d+|0x[0-9a-fA-F]+", nxt):
                code = self.number("an exception code")
                return lambda o: o.get("kind") == "exception" and o.get("exception_code") == code
            return lambda o: o.get("kind") == "exception"
        if low in _EVENTS:
            return lambda o: o.get("event") == low
        if low in _KINDS:
            return lambda o: o.get("kind") == low
        if low == "crc":
            return lambda o: o.get("kind") == "noise" and "CRC" in " ".join(o.get("notes") or ())
        if low in ("fc", "unit"):
            values = (parse_fcs if low == "fc" else lambda t: parse_units([t]))(
                self.take(low + " values")
            )
            key = low
            return lambda o: o.get(key) in values
        if low == "address":
            lo, hi = parse_range(self.take("an address or range"))
            return lambda o: (
                o.get("kind") in ("request", "response", "exception") and touches(o, lo, hi)
            )
        if low == "latency":
            op = self.compare()
            from mbmon.timefmt import TimeParseError, parse_duration

            value = self.take("a time (50ms)")
            try:
                limit_ms = parse_duration(value) * 1000.0
            except TimeParseError as exc:
                raise FilterError(f"latency: {exc}") from None
            return lambda o: o.get("latency_ms") is not None and op(o["latency_ms"], limit_ms)
        item = _ITEM.match(token)
        if item:
            table = _TABLES[item.group(1).upper()]
            at = int(item.group(2))
            op = self.compare()
            wanted = self.number("a number")
            return lambda o: _carries(o, table, at, op, wanted)
        raise FilterError(f"unknown test {token!r} in {self.text!r} (see --help: expressions)")


def _carries(
    obj: Mapping[str, Any], table: str, at: int, op: Callable[[Any, Any], bool], wanted: int
) -> bool:
    """Whether a frame's values include item ``at`` of ``table`` and it compares to
    ``wanted`` (a read's answer, a write request or its echo)."""
    from mbmon.protocol.pdu import table_of

    values = obj.get("values")
    address = obj.get("address")
    fc = obj.get("fc")
    if not values or not isinstance(address, int) or fc is None or table_of(fc) != table:
        return False
    index = at - address
    return 0 <= index < len(values) and bool(op(values[index], wanted))


# --------------------------------------------------------------------------- pacing


class Pacer:
    """Hold output back to ``speed`` times the original pace.

    Every record's due time is computed from one monotonic start and the first
    record's capture time (start + (ts - ts0) / speed), so sleeping late once
    never accumulates into drift over a long replay.
    """

    def __init__(
        self,
        speed: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
        self.speed = speed
        self._clock = clock
        self._sleep = sleep
        self._start: float | None = None
        self._ts0 = 0.0

    def wait(self, ts: float) -> None:
        """Return when the record captured at ``ts`` is due."""
        if self._start is None:
            self._start = self._clock()
            self._ts0 = ts
            return
        due = self._start + (ts - self._ts0) / self.speed
        delay = due - self._clock()
        if delay > 0:
            self._sleep(delay)
