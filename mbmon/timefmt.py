"""One home for time: how capture times print (``-t``), how spans read, how times parse.

Owns the time basis every command shares (``read``, ``replay``, ``info``,
``export .txt``): :class:`TimeFormat` prints a capture time in one of the
modes of tshark's ``-t`` option, :func:`parse_when` reads back every form it
prints (for ``--since``/``--until``), :func:`human_span` writes a duration in
human units, and :func:`add_time_option` adds the ``-t`` option to a command.

Modes (:data:`TIME_MODES`):

- ``a``  absolute local time of day, ``12:00:05.123456`` (the default); the
  date is added automatically to the times of a capture that spans more than
  one day (:meth:`TimeFormat.for_span`; while streaming: to every time that
  falls on another day than the first one);
- ``ad`` absolute local date and time, ``2024-05-01 12:00:05.123456``;
- ``r``  seconds relative to the first frame, ``12.500000``;
- ``e``  epoch seconds, ``1714564805.123456``;
- ``u``/``ud`` as ``a``/``ad``, in UTC (and ``--since``/``--until`` read in UTC).

Any float prints: a time no calendar can show (before year 1, after 9999, a
pcapng timestamp of 1e17 s, NaN, infinity) prints as epoch seconds in every
mode but ``r`` (``100000000000000000.000000``, ``1.000000e+20``, ``nan``),
which :func:`parse_when` also accepts.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import re
import time
from typing import Any

#: the ``-t`` modes, in the order ``--help`` lists them
TIME_MODES = ("a", "ad", "r", "e", "u", "ud")
DEFAULT_MODE = "a"

#: the range of times a calendar shows (years 1..9999, a day of margin for time zones)
CALENDAR_MIN = -62135596800.0 + 86400.0
CALENDAR_MAX = 253402300800.0 - 86400.0

_DATE = "%04d-%02d-%02d "
_CLOCK = "%02d:%02d:%02d."


def epoch_text(value: float) -> str:
    """``value`` as epoch seconds with microseconds, for any float (the fallback form)."""
    if not math.isfinite(value):
        return str(value)  # nan, inf, -inf
    if abs(value) < 1e15:
        return "%.6f" % value  # noqa: UP031
    return "%.6e" % value  # noqa: UP031


class TimeFormat:
    """How capture times print: one ``-t`` mode, its origin and its date rule.

    ``origin`` is the first frame's time (the zero of ``r`` and the first day of
    the automatic date); unset, it is the first time printed. ``date`` forces the
    date on (``ad``/``ud`` do it themselves); ``auto_date`` adds it to times that
    fall on another day than the origin's (modes ``a`` and ``u``).

    The text of a time is a per-second prefix (cached: one calendar conversion
    per second of capture, not per record) and six digits of microseconds, in
    every mode but ``r`` and the fallback. ``_second`` is that cache,
    ``[second, prefix, prefix in UTF-8]`` (prefix ``None``: the time has no such
    form, :meth:`text` computes it whole); the fused reader uses it directly.
    """

    __slots__ = ("_day", "_second", "_utc", "auto_date", "date", "mode", "origin")

    def __init__(
        self,
        mode: str = DEFAULT_MODE,
        *,
        origin: float | None = None,
        date: bool = False,
        auto_date: bool = True,
    ) -> None:
        if mode not in TIME_MODES:
            raise ValueError(f"unknown time format {mode!r}; use one of {', '.join(TIME_MODES)}")
        self.mode = mode
        self.origin = origin
        self.date = date or mode in ("ad", "ud")
        self.auto_date = auto_date
        self._utc = mode in ("u", "ud")
        self._day: tuple[int, int] | None = None
        self._second: list[Any] = [None, None, None]
        if origin is not None and math.isfinite(origin):
            self._day = self._day_of(origin)

    @classmethod
    def for_span(cls, mode: str, start: float | None, end: float | None) -> TimeFormat:
        """The format for a capture known from ``start`` to ``end`` (a log): relative
        times from ``start``, the date on every time when the span crosses midnight."""
        fmt = cls(mode, origin=start)
        if start is not None and end is not None and mode in ("a", "u"):
            first, last = fmt._day_of(start), fmt._day_of(end)
            if first is not None and last is not None and first != last:
                fmt.date = True
        return fmt

    def __repr__(self) -> str:
        return f"TimeFormat({self.mode!r}, origin={self.origin!r}, date={self.date!r})"

    @property
    def per_second(self) -> bool:
        """Whether times print as a cached per-second prefix and microseconds (not ``r``)."""
        return self.mode != "r"

    @property
    def utc(self) -> bool:
        return self._utc

    def _day_of(self, ts: float) -> tuple[int, int] | None:
        if not CALENDAR_MIN <= ts < CALENDAR_MAX:
            return None
        try:
            tm = time.gmtime(int(ts // 1)) if self._utc else time.localtime(int(ts // 1))
        except (OverflowError, OSError, ValueError):
            return None
        return tm.tm_year, tm.tm_yday

    def _new_second(self, ts: float, whole: float) -> None:
        """Fill the per-second cache for the second ``whole`` (``ts // 1``)."""
        cache = self._second
        cache[0] = whole
        prefix: str | None = None
        if self.mode == "e":
            if 0.0 <= whole < 1e15:
                prefix = "%d." % whole  # noqa: UP031
        elif self.mode != "r" and CALENDAR_MIN <= whole < CALENDAR_MAX:
            try:
                tm = time.gmtime(int(whole)) if self._utc else time.localtime(int(whole))
            except (OverflowError, OSError, ValueError):
                tm = None
            if tm is not None:
                prefix = _CLOCK % (tm.tm_hour, tm.tm_min, tm.tm_sec)
                show_date = self.date
                if not show_date and self.auto_date:
                    day = (tm.tm_year, tm.tm_yday)
                    if self._day is None:
                        self._day = day
                    show_date = day != self._day
                if show_date:
                    prefix = _DATE % (tm.tm_year, tm.tm_mon, tm.tm_mday) + prefix
        cache[1] = prefix
        cache[2] = prefix.encode() if prefix is not None else None

    def text(self, ts: float) -> str:
        """The text of capture time ``ts`` (epoch seconds) in this format: any float prints."""
        whole = ts // 1
        cache = self._second
        if cache[0] != whole:  # one calendar conversion per second of capture
            self._new_second(ts, whole)
        prefix = cache[1]
        if prefix is None:
            return self._whole_text(ts)
        # %d truncates, so +0.5 rounds to the microsecond a float timestamp stands for
        # (1700000000.26 is 0.2599999 s after the second); min() keeps a nanosecond
        # .9999996 in this second. %-formatting is about twice as fast as an f-string.
        return "%s%06d" % (prefix, min((ts - whole) * 1e6 + 0.5, 999999))  # noqa: UP031

    def bytes(self, ts: float) -> bytes:
        """:meth:`text` in UTF-8."""
        whole = ts // 1
        cache = self._second
        if cache[0] != whole:
            self._new_second(ts, whole)
        prefix = cache[2]
        if prefix is None:
            return self._whole_text(ts).encode()
        return b"%b%06d" % (prefix, min((ts - whole) * 1e6 + 0.5, 999999))

    def _whole_text(self, ts: float) -> str:
        """A time without a per-second form: relative (``r``) or the epoch fallback."""
        if self.mode == "r":
            if self.origin is None and math.isfinite(ts):
                self.origin = ts
            return epoch_text(ts - self.origin if self.origin is not None else ts)
        return epoch_text(ts)


def human_span(seconds: float) -> str:
    """A duration in human units: ``250 ms``, ``12.5 s``, ``3 min 02.25 s``,
    ``2 h 03 min 12.5 s``, ``3 d 00 h 10 min 00 s`` (any float prints)."""
    if not math.isfinite(seconds) or abs(seconds) >= 1e12:
        return f"{seconds:.6g} s"
    sign = "-" if seconds < 0 else ""
    s = abs(seconds)
    if s < 1.0:
        ms = f"{s * 1000:.3f}".rstrip("0").rstrip(".")
        return f"{sign}{ms} ms"
    days, rest = divmod(s, 86400.0)
    hours, rest = divmod(rest, 3600.0)
    minutes, secs = divmod(rest, 60.0)
    text = f"{secs:.3f}".rstrip("0").rstrip(".")
    parts: list[str] = []
    if days:
        parts.append(f"{int(days)} d")
    if days or hours:
        parts.append(f"{int(hours):02d} h" if parts else f"{int(hours)} h")
    if days or hours or minutes:
        parts.append(f"{int(minutes):02d} min" if parts else f"{int(minutes)} min")
        if secs < 10:
            text = "0" + text
    parts.append(f"{text} s")
    return sign + " ".join(parts)


# --------------------------------------------------------------------------- parsing


class TimeParseError(ValueError):
    """A time that cannot be understood (a usage error)."""


_OFFSET = re.compile(r"^\+?\s*((?:\d+(?:\.\d*)?|\.\d+)\s*(?:ms|min|s|m|h)?\s*)+$")
_PART = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*(ms|min|s|m|h)?")
_UNIT = {"ms": 0.001, "s": 1.0, "": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
_EPOCH = re.compile(r"\d{9,}(\.\d*)?")
_FLOAT = re.compile(r"-?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?|-?(nan|inf)", re.IGNORECASE)
_CLOCK_RE = re.compile(r"\d{1,2}:\d{2}(:\d{2}(\.\d+)?)?")


_DURATION = re.compile(r"^\s*((?:\d+(?:\.\d*)?|\.\d+)\s*(?:ms|min|s|m|h|d)?\s*)+$")
_DURATION_PART = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*(ms|min|s|m|h|d)?")


def parse_duration(text: str) -> float:
    """A length of time as seconds: ``30s``, ``250ms``, ``1m30s``, ``1h``, ``7d``
    (a bare number is seconds; ``m`` and ``min`` are minutes), the units the
    offsets of :func:`parse_when` use plus ``d``; :class:`TimeParseError` when
    it is none or is 0."""
    value = text.strip()
    if not _DURATION.match(value):
        raise TimeParseError(f"not a duration: {text!r} (e.g. 30s, 250ms, 1m30s, 1h, 7d)")
    units = {**_UNIT, "d": 86400.0}
    seconds = sum(float(n) * units[u] for n, u in _DURATION_PART.findall(value))
    if not seconds > 0:
        raise TimeParseError(f"a duration must be more than 0: {text!r}")
    return seconds


def parse_when(text: str, start: float | None, fmt: TimeFormat | None = None) -> float:
    """A ``--since``/``--until`` value as epoch seconds; accepts every form
    :class:`TimeFormat` prints.

    - an offset from the start (``+5s``, ``+1m30s``, ``+250ms``, ``2.5``: seconds;
      what ``-t r`` prints);
    - a time of day (``12:00:05.123456``, what ``-t a``/``u`` print), on the first
      day of the capture;
    - a date and time (``2024-05-01 12:00:05.123456`` or ISO 8601 with ``T``, what
      ``-t ad``/``ud`` print), local time unless it says otherwise;
    - epoch seconds (9 digits or more, a negative number or one with an exponent:
      what ``-t e`` and the fallback print).

    ``start`` is the first frame's time; ``fmt`` the output's time format: with
    ``u``/``ud``, times of day and dates without a zone are UTC; with ``r`` a bare
    number is always an offset, with ``e`` always epoch seconds.
    """
    value = text.strip()
    if not value:
        raise TimeParseError("empty time")
    utc = fmt is not None and fmt.utc
    mode = fmt.mode if fmt is not None else None
    if mode in ("r", "e") and _FLOAT.fullmatch(value):  # a bare number as that mode prints
        if mode == "e":
            return float(value)
        if start is None:
            raise TimeParseError("there are no records to measure an offset from")
        return start + float(value)
    if value.startswith("+") or (_OFFSET.match(value) and not _EPOCH.fullmatch(value)):
        if not _OFFSET.match(value):
            raise TimeParseError(f"not an offset: {text!r} (e.g. +5s, +1m30s, +250ms)")
        offset = sum(float(n) * _UNIT[u] for n, u in _PART.findall(value))
        if start is None:
            raise TimeParseError("there are no records to measure an offset from")
        return start + offset
    if _EPOCH.fullmatch(value) or _FLOAT.fullmatch(value):
        return float(value)
    tz = _dt.UTC if utc else None
    if _CLOCK_RE.fullmatch(value):
        if start is None:
            raise TimeParseError("there are no records to take the day from")
        if not CALENDAR_MIN <= start < CALENDAR_MAX:
            raise TimeParseError("the first record's time has no calendar day")
        day = _dt.datetime.fromtimestamp(start, tz).date()
        try:
            clock = _dt.time.fromisoformat(value if value.count(":") == 2 else value + ":00")
        except ValueError:
            raise TimeParseError(f"not a time of day: {text!r}") from None
        return _dt.datetime.combine(day, clock, tz).timestamp()
    try:
        moment = _dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise TimeParseError(
            f"not a time: {text!r} (use +5s, 12:00:05, 2024-05-01 12:00:05 or epoch seconds)"
        ) from None
    if moment.tzinfo is None and tz is not None:
        moment = moment.replace(tzinfo=tz)
    return moment.timestamp()


# --------------------------------------------------------------------------- the option

TIME_HELP = (
    "how times print: a = local time of day (default; the date is added when the "
    "capture spans more than one day), ad = local date and time, r = seconds since the "
    "first frame, e = epoch seconds, u / ud = as a / ad in UTC. --since/--until accept "
    "what it prints."
)
_SINCE_UNTIL = " --since/--until accept what it prints."


def add_time_option(parser: argparse.ArgumentParser | Any, *, since_until: bool = True) -> None:
    """Add ``-t {a,ad,r,e,u,ud}`` (dest ``time_format``, default ``a``) to a command;
    ``since_until=False`` for a command without ``--since/--until`` (its help must
    not name them)."""
    parser.add_argument(
        "-t",
        "--time-format",
        dest="time_format",
        choices=TIME_MODES,
        default=DEFAULT_MODE,
        metavar="{" + ",".join(TIME_MODES) + "}",
        help=TIME_HELP if since_until else TIME_HELP.removesuffix(_SINCE_UNTIL),
    )


#: every form :class:`TimeFormat` prints, as the head of a monitor line
_PRINTED = re.compile(
    r"(\d{4}-\d{2}-\d{2} )?\d{2}:\d{2}:\d{2}\.\d{6}|-?\d+\.\d{6}(e[-+]\d+)?|-?(nan|inf)"
)


def replace_time(line: str, text: str) -> str:
    """A monitor line with its leading time (any form :class:`TimeFormat` prints, up
    to the first two spaces) replaced by ``text``; other lines come back as they are."""
    head, sep, rest = line.partition("  ")
    if not sep or not _PRINTED.fullmatch(head):
        return line
    return text + sep + rest
