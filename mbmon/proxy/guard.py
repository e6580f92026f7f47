"""The proxy's write guard and client filter: pure decisions, no I/O.

:class:`Guard` decides, for one decoded request, whether the proxy forwards it
or refuses it (answering the client itself). It knows which function codes
write and what they write:

=====  ===========================  ==========================================
fc     writes                       address range checked
=====  ===========================  ==========================================
05     one coil                     ``coil`` address
06     one holding register         ``hr`` address
0F     coils                        ``coil`` address .. address + count - 1
10     holding registers            ``hr`` address .. address + count - 1
15     file records                 none (only ``unit:`` terms apply)
16     one holding register (mask)  ``hr`` address
17     holding registers (its       ``hr`` write address .. + write count - 1
       write part; the read part
       is never refused)
=====  ===========================  ==========================================

A write whose fields disagree (byte count, quantity and length; a range that runs
past 0xFFFF; truncated) is refused as malformed (rule ``malformed``) whenever the
guard is on: its range cannot be trusted.

``--read-only`` is an allow-list: only what is known to be a read passes --
01-04, 07, 0B, 0C, 11, 14, 18, 2B/0E (Read Device Identification), and of the
Diagnostics (08) sub-functions 00 (Return Query Data), 02 (diagnostic register)
and 0B-12 (the counters). Everything else (08/01 restart communications, 08/04
force listen-only, 08/0A clear counters, user-defined codes 65-72 and 100-110,
unknown codes) is refused (rule ``read-only``) and audited, unless ``--allow-fc``
opens it: ``--allow-fc CODE`` (every sub-function), ``--allow-fc CODE/SUB``
(08/SUB, 2B/MEI type), ``--allow-fc A-B`` (a range of codes); numbers decimal or
0x hex (``65-72``, ``0x41``, ``8/1``, ``0x2B/0x0D``). Writes stay judged by the
write specs. Without ``--read-only`` codes that do not write are not refused.

Specs (``--allow-write`` / ``--deny-write``): comma-joined terms that must all
match, each ``TABLE:A`` or ``TABLE:A-B`` (inclusive, decimal or 0x hex):
``hr:100``, ``hr:200-251``, ``coil:0-7``, ``unit:2``, ``unit:2,hr:100-110``.
A spec without a ``unit:`` term applies to every unit; a spec without a table
term applies to every table (and to 0x15 file-record writes).

Precedence, in order:

1. a write that touches any address of a ``--deny-write`` spec is refused
   (rule ``deny-write SPEC``);
2. with ``--read-only`` or any ``--allow-write``, a write is forwarded only
   when every address it writes is covered by the ``--allow-write`` specs
   (together), else refused (rule ``read-only`` or ``not in --allow-write``);
3. otherwise it is forwarded.

So ``--read-only --allow-write hr:200-251`` lets only R200..R251 be written,
and ``--deny-write`` always wins over ``--allow-write``.

``--allow-from CIDR`` (:class:`ClientFilter`) admits only clients whose
address is inside one of the networks.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from mbmon.model import Pdu
from mbmon.protocol.functions import FUNCTIONS, derived
from mbmon.protocol.pdu import decode_pdu

__all__ = [
    "COIL",
    "HOLDING",
    "KNOWN_READS",
    "ClientFilter",
    "FcRule",
    "Guard",
    "GuardSpecError",
    "Verdict",
    "WriteSpec",
    "WriteTarget",
    "is_write",
    "parse_fc",
    "parse_spec",
    "write_target",
]

HOLDING = "hr"
COIL = "coil"

#: Function codes that write, and the table they write (``None``: file records), from
#: the one function-code table (:mod:`mbmon.protocol.functions`).
_WRITE_TABLE: dict[int, str | None] = {}

#: Function codes known to only read, that ``--read-only`` lets through: code -> the
#: sub-functions that read (``None``: all). From the table: a ``read`` that does not
#: write, or a code whose ``only_reads`` says so (0x08: Return Query Data, the
#: diagnostic register and the counters; 0x2B: Read Device Identification).
KNOWN_READS: dict[int, frozenset[int] | None] = {}

#: Codes that always pass unchecked while no write spec or ``--read-only`` restricts
#: anything but reads: the guard's fast path decodes nothing for them.
_PLAIN_READS: set[int] = set()

#: Codes with a sub-function (08) or MEI type (2B): how many bytes it takes.
_SUB_BYTES: dict[int, int] = {}

#: Shapes whose request writes one item at its address (05, 06, 16).
_ONE_ITEM = frozenset({"write_single", "mask_write"})


@derived
def _from_table() -> None:
    """The guard's view of the function-code table (again whenever a code is
    registered)."""
    _WRITE_TABLE.clear()
    KNOWN_READS.clear()
    _SUB_BYTES.clear()
    for code, spec in FUNCTIONS.items():
        if spec.writes:
            _WRITE_TABLE[code] = (
                None if spec.table is None else COIL if spec.table == "coil" else HOLDING
            )
        elif spec.only_reads is True or spec.read:
            KNOWN_READS[code] = None
        elif spec.only_reads:
            KNOWN_READS[code] = frozenset(spec.only_reads)
        if spec.sub_bytes:
            _SUB_BYTES[code] = spec.sub_bytes
    _PLAIN_READS.clear()
    _PLAIN_READS.update(code for code, subs in KNOWN_READS.items() if subs is None)


#: Spec table names and their aliases.
_TABLE_NAMES = {
    "hr": HOLDING,
    "holding": HOLDING,
    "holding_register": HOLDING,
    "coil": COIL,
    "coils": COIL,
}


class GuardSpecError(ValueError):
    """A spec or CIDR that cannot be parsed; the message says which part and why."""


def is_write(fc: int) -> bool:
    """Whether function code ``fc`` writes (the table's ``writes``: 05, 06, 0F, 10, 15,
    16, 17 and any registered code that writes)."""
    return fc in _WRITE_TABLE


@dataclass(frozen=True, slots=True)
class WriteTarget:
    """What one request writes: the table (``None`` for file records) and the
    address range ``first..last`` (``None`` when unknown or not addressed)."""

    fc: int
    table: str | None
    first: int | None
    last: int | None

    @property
    def count(self) -> int | None:
        if self.first is None or self.last is None:
            return None
        return self.last - self.first + 1


def write_target(pdu: Pdu) -> WriteTarget | None:
    """What the request ``pdu`` writes, or ``None`` when it does not write. Where it
    writes comes from its row of the function-code table: file records (no table)
    have no range, a read/write (0x17) writes its write part, a single write or
    mask write one item, the others ``count`` items."""
    fc = pdu.fc
    if fc not in _WRITE_TABLE:
        return None
    table = _WRITE_TABLE[fc]
    shape = FUNCTIONS[fc].shape
    if table is None:
        return WriteTarget(fc, None, None, None)
    if shape == "read_write":
        address = pdu.fields.get("write_address")
        count = pdu.fields.get("write_count")
    else:
        address = pdu.address
        count = 1 if shape in _ONE_ITEM else pdu.count
    if not isinstance(address, int) or not isinstance(count, int) or count < 1:
        # truncated or malformed: an unknown range is judged as if it touched the
        # whole table (deny specs hit it, allow specs must cover everything)
        return WriteTarget(fc, table, 0, 0xFFFF)
    return WriteTarget(fc, table, address, address + count - 1)


@dataclass(frozen=True, slots=True)
class WriteSpec:
    """One ``--allow-write``/``--deny-write`` value: units and one address range
    of one table; ``None`` parts match everything."""

    text: str
    units: tuple[int, int] | None = None
    table: str | None = None
    first: int = 0
    last: int = 0xFFFF

    def matches_unit(self, unit: int) -> bool:
        return self.units is None or self.units[0] <= unit <= self.units[1]

    def overlaps(self, unit: int, target: WriteTarget) -> bool:
        """Whether the write touches at least one address this spec names."""
        if not self.matches_unit(unit):
            return False
        if self.table is None:
            return True
        if target.table != self.table or target.first is None or target.last is None:
            return False
        return target.first <= self.last and self.first <= target.last

    def covered(self, unit: int, target: WriteTarget) -> list[tuple[int, int]] | None:
        """The part of the write's range this spec covers (``[]`` for none);
        ``None`` when it covers the whole write."""
        if not self.matches_unit(unit):
            return []
        if self.table is None:
            return None
        if target.table != self.table or target.first is None or target.last is None:
            return []
        lo, hi = max(target.first, self.first), min(target.last, self.last)
        if lo > hi:
            return []
        if lo == target.first and hi == target.last:
            return None
        return [(lo, hi)]


def _number(text: str, what: str, spec: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise GuardSpecError(f"{spec!r}: {what} {text!r} is not a number") from None


def _range(text: str, what: str, spec: str, top: int) -> tuple[int, int]:
    lo_text, sep, hi_text = text.partition("-")
    lo = _number(lo_text.strip(), what, spec)
    hi = _number(hi_text.strip(), what, spec) if sep else lo
    if not 0 <= lo <= top or not 0 <= hi <= top:
        raise GuardSpecError(f"{spec!r}: {what} {text!r} outside 0..{top}")
    if hi < lo:
        raise GuardSpecError(f"{spec!r}: range {text!r} runs backwards")
    return lo, hi


def parse_spec(text: str) -> WriteSpec:
    """Parse ``hr:100``, ``hr:200-251``, ``coil:0-7``, ``unit:2``, ``unit:1-3,hr:0x10``."""
    spec = text.strip()
    if not spec:
        raise GuardSpecError("empty write spec")
    units: tuple[int, int] | None = None
    table: str | None = None
    first, last = 0, 0xFFFF
    for term in spec.split(","):
        name, sep, value = term.strip().partition(":")
        name = name.strip().lower()
        if not sep or not value.strip():
            raise GuardSpecError(
                f"{spec!r}: term {term.strip()!r} is not NAME:A or NAME:A-B "
                "(hr:100, coil:0-7, unit:2)"
            )
        if name == "unit":
            if units is not None:
                raise GuardSpecError(f"{spec!r}: more than one unit term")
            units = _range(value, "unit", spec, 0xFF)
        elif name in _TABLE_NAMES:
            if table is not None:
                raise GuardSpecError(f"{spec!r}: more than one table term")
            table = _TABLE_NAMES[name]
            first, last = _range(value, "address", spec, 0xFFFF)
        else:
            known = ", ".join(["unit", *sorted(_TABLE_NAMES)])
            raise GuardSpecError(f"{spec!r}: unknown term {name!r} (use {known})")
    return WriteSpec(spec, units, table, first, last)


@dataclass(frozen=True, slots=True)
class FcRule:
    """One ``--allow-fc`` value: function codes ``first..last``, and one sub-function
    (08) or MEI type (2B), ``None`` for all."""

    text: str
    first: int
    last: int
    sub: int | None = None

    def opens(self, fc: int, sub: int | None) -> bool:
        return self.first <= fc <= self.last and (self.sub is None or self.sub == sub)


def _code(text: str, what: str, spec: str, top: int) -> int:
    """A number of an ``--allow-fc`` value: decimal (leading zeros allowed) or 0x hex."""
    t = text.strip().lower()
    try:
        value = int(t[2:], 16) if t.startswith("0x") else int(t, 10)
    except ValueError:
        raise GuardSpecError(
            f"--allow-fc {spec!r}: {what} {text.strip()!r} is not a number (decimal, or "
            "hex as 0x2B)"
        ) from None
    if not 0 <= value <= top:
        raise GuardSpecError(f"--allow-fc {spec!r}: {what} {value} outside 0..{top}")
    return value


def parse_fc(text: str) -> FcRule:
    """Parse an ``--allow-fc`` value: ``65``, ``65-72``, ``0x41``, ``8/1``, ``0x2B/0x0D``."""
    spec = text.strip()
    code, sep, sub_text = spec.partition("/")
    lo_text, dash, hi_text = code.partition("-")
    first = _code(lo_text, "function code", spec, 0x7F)
    last = _code(hi_text, "function code", spec, 0x7F) if dash else first
    if last < first:
        raise GuardSpecError(f"--allow-fc {spec!r}: range runs backwards")
    if first == 0:
        raise GuardSpecError(f"--allow-fc {spec!r}: there is no function code 0")
    sub = None
    if sep:
        width = _SUB_BYTES.get(first, 0)
        if last != first or not width:
            raise GuardSpecError(
                f"--allow-fc {spec!r}: CODE/SUB names a Diagnostics (8/SUB) sub-function "
                "or an MEI type (0x2B/TYPE)"
            )
        sub = _code(sub_text, "sub-function", spec, (1 << 8 * width) - 1)
    for fc in range(first, last + 1):
        if fc in _WRITE_TABLE:
            raise GuardSpecError(
                f"--allow-fc {spec!r}: 0x{fc:02X} writes; writes are opened by --allow-write"
            )
    return FcRule(spec, first, last, sub)


def sub_function(pdu: bytes | bytearray | memoryview) -> int | None:
    """The sub-function (08) or MEI type (2B) of a request PDU (function code first),
    as wide as the function-code table says (``sub_bytes``); ``None`` for codes
    without one or when the PDU is too short to have it."""
    width = _SUB_BYTES.get(pdu[0], 0) if pdu else 0
    if not width or len(pdu) < 1 + width:
        return None
    return int.from_bytes(pdu[1 : 1 + width], "big")


@dataclass(frozen=True, slots=True)
class Verdict:
    """A refusal: the rule that refused and the audit fields (see :meth:`Guard.check`)."""

    rule: str
    message: str
    info: Mapping[str, Any]


def _cover(ranges: Iterable[tuple[int, int]], first: int, last: int) -> bool:
    """Whether the union of ``ranges`` covers ``first..last``."""
    at = first
    for lo, hi in sorted(ranges):
        if lo > at:
            return False
        if hi >= at:
            at = hi + 1
            if at > last:
                return True
    return at > last


@dataclass(frozen=True)
class Guard:
    """The write policy: ``read_only``, ``allow`` and ``deny`` specs (module text)."""

    read_only: bool = False
    allow: tuple[WriteSpec, ...] = ()
    deny: tuple[WriteSpec, ...] = ()
    exception_code: int = 0x01
    allow_fc: tuple[FcRule, ...] = ()
    _restricted: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_restricted", self.read_only or bool(self.allow))

    @classmethod
    def from_options(
        cls,
        read_only: bool,
        allow: Sequence[str],
        deny: Sequence[str],
        exception_code: int = 0x01,
        allow_fc: Sequence[str] = (),
    ) -> Guard:
        """A guard from command-line values; :class:`GuardSpecError` for a bad spec."""
        if not 1 <= exception_code <= 0xFF:
            raise GuardSpecError(f"exception code {exception_code} outside 1..255")
        if allow_fc and not read_only:
            raise GuardSpecError(
                "--allow-fc opens codes that --read-only refuses; without --read-only "
                "codes that do not write already pass"
            )
        return cls(
            read_only,
            tuple(parse_spec(s) for s in allow),
            tuple(parse_spec(s) for s in deny),
            exception_code,
            tuple(parse_fc(s) for s in allow_fc),
        )

    @property
    def active(self) -> bool:
        """Whether the guard can refuse anything at all."""
        return self._restricted or bool(self.deny)

    def describe(self) -> str:
        """One line for the start-up message: what the guard does."""
        parts = []
        if self.read_only:
            parts.append("read-only")
        parts.extend(f"allow-fc {r.text}" for r in self.allow_fc)
        parts.extend(f"allow-write {s.text}" for s in self.allow)
        parts.extend(f"deny-write {s.text}" for s in self.deny)
        return ", ".join(parts) if parts else "off"

    def check_raw(self, unit: int, pdu: bytes) -> Verdict | None:
        """:meth:`check` for the request PDU bytes ``pdu``: the codes known to read
        whatever their sub-function (01-04, 07, 0B, 0C, 11, 14, 18 and registered
        reads) pass without being decoded."""
        if pdu and pdu[0] in _PLAIN_READS:
            return None
        return self.check(unit, decode_pdu(pdu, False))

    def check(self, unit: int, pdu: Pdu) -> Verdict | None:
        """``None`` to forward the request ``pdu`` for ``unit``; else the refusal.

        The verdict's ``info`` holds ``rule``, ``fc``, ``unit``, ``address``
        and ``count`` (the written range; ``None`` for file records and codes
        that do not write; ``sub_function`` for 08 and 2B).
        """
        if not self.active:
            return None
        target = write_target(pdu)
        if target is None:
            if self.read_only:
                return self._read_only(unit, pdu)
            return None
        if pdu.malformed is not None:
            return self._verdict("malformed", unit, target, pdu.malformed)
        for spec in self.deny:
            if spec.overlaps(unit, target):
                return self._verdict(f"deny-write {spec.text}", unit, target)
        if not self._restricted:
            return None
        if self._allowed(unit, target):
            return None
        rule = "read-only" if self.read_only else "not in --allow-write"
        return self._verdict(rule, unit, target)

    def _allowed(self, unit: int, target: WriteTarget) -> bool:
        pieces: list[tuple[int, int]] = []
        for spec in self.allow:
            part = spec.covered(unit, target)
            if part is None:
                return True
            pieces.extend(part)
        if not pieces or target.first is None or target.last is None:
            return False
        return _cover(pieces, target.first, target.last)

    def _read_only(self, unit: int, pdu: Pdu) -> Verdict | None:
        """Under ``--read-only``, a code that does not write passes only when it is a
        known read (:data:`KNOWN_READS`) or ``--allow-fc`` opens it."""
        fc = pdu.fc
        sub = sub_function(pdu.raw)
        if fc in KNOWN_READS:
            subs = KNOWN_READS[fc]
            if subs is None or sub in subs:
                return None
        for rule in self.allow_fc:
            if rule.opens(fc, sub):
                return None
        name = FUNCTIONS[fc].name if fc in FUNCTIONS else "user-defined or unknown code"
        what = f"0x{fc:02X}" + ("" if sub is None else f"/0x{sub:02X}")
        message = (
            f"refused {what} ({name}) on unit {unit} (read-only: not a known read; "
            "--allow-fc opens it)"
        )
        info: dict[str, Any] = {
            "rule": "read-only",
            "fc": fc,
            "unit": unit,
            "address": None,
            "count": None,
        }
        if sub is not None:
            info["sub_function"] = sub
        return Verdict("read-only", message, info)

    def _verdict(
        self, rule: str, unit: int, target: WriteTarget, why: str | None = None
    ) -> Verdict:
        where = ""
        if target.table is not None and target.first is not None and target.last is not None:
            prefix = "R" if target.table == HOLDING else "coil "
            where = f" {prefix}{target.first}" + (
                f"..{target.last}" if target.last != target.first else ""
            )
        detail = rule if why is None else f"{rule}: {why}"
        message = f"refused 0x{target.fc:02X} write{where} on unit {unit} ({detail})"
        info = {
            "rule": rule,
            "fc": target.fc,
            "unit": unit,
            "address": target.first,
            "count": target.count,
        }
        if why is not None:
            info["reason"] = why
        return Verdict(rule, message, info)


class ClientFilter:
    """``--allow-from`` networks: which client addresses may connect (all when empty)."""

    def __init__(self, cidrs: Sequence[str] = ()) -> None:
        nets = []
        for text in cidrs:
            try:
                nets.append(ipaddress.ip_network(text.strip(), strict=False))
            except ValueError:
                raise GuardSpecError(f"--allow-from {text!r}: not an address or CIDR") from None
        self.networks = tuple(nets)

    def allows(self, host: str) -> bool:
        """Whether a client at ``host`` (an IP address text) may connect."""
        if not self.networks:
            return True
        try:
            addr = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        mapped = getattr(addr, "ipv4_mapped", None)
        candidates = [addr] if mapped is None else [addr, mapped]
        return any(
            a in net for a in candidates for net in self.networks if a.version == net.version
        )
