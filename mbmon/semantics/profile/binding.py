"""Which profile applies to which server endpoint and unit id (``--profile`` bindings)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mbmon.semantics.profile.dump import dump_profile
from mbmon.semantics.profile.load import load_profile
from mbmon.semantics.profile.model import Profile, ProfileError

if TYPE_CHECKING:
    from mbmon.model import Stream


def split_endpoint(endpoint: str) -> tuple[str, int | None]:
    """(host, port) of ``IP:PORT`` / ``[v6]:PORT``; a serial port name is all host."""
    if endpoint.startswith("["):
        host, _, rest = endpoint[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
        return host, int(port) if port.isdigit() else None
    if endpoint.count(":") == 1:
        host, _, port = endpoint.partition(":")
        if port.isdigit():
            return host, int(port)
    return endpoint, None


@dataclass(frozen=True, slots=True)
class _Rule:
    spec: str
    profile: Profile
    unit: int | None = None
    host: str | None = None
    port: int | None = None


class ProfileBinding:
    """Which profile applies to which server endpoint and unit (CLI ``--profile`` values).

    Precedence, most specific first: ``unit:N=NAME`` > ``HOST:PORT=NAME`` >
    ``HOST=NAME`` > plain ``NAME_OR_FILE`` (default for everything). A later
    spec of the same kind replaces an earlier one.
    """

    def __init__(self, rules: Iterable[_Rule] = ()) -> None:
        self._units: dict[int, Profile] = {}
        self._hostports: dict[tuple[str, int], Profile] = {}
        self._hosts: dict[str, Profile] = {}
        self._default: Profile | None = None
        self._profiles: dict[int, Profile] = {}  # id -> profile, for sources()
        self._cache: dict[tuple[str, int], Profile | None] = {}
        for r in rules:
            self._add(r)

    @classmethod
    def parse(
        cls, specs: Iterable[str], *, loader: Callable[[str], Profile] = load_profile
    ) -> ProfileBinding:
        """Build from ``--profile`` values; each distinct name or file is loaded once.

        ``loader`` turns the name or file after ``=`` into a profile (default:
        :func:`~mbmon.semantics.profile.load.load_profile`, built-ins and files).
        """
        loaded: dict[str, Profile] = {}

        def get(name: str, spec: str) -> Profile:
            if not name:
                raise ProfileError(f"--profile {spec!r}: no profile name or file after '='")
            if name not in loaded:
                loaded[name] = loader(name)
            return loaded[name]

        return cls([_rule(spec, get) for spec in specs])

    @classmethod
    def from_profiles(cls, bound: Iterable[tuple[str, Profile]]) -> ProfileBinding:
        """Build from ``--profile`` specs whose profiles are already loaded.

        Each ``(spec, profile)`` binds ``profile`` to the target the spec names
        (``unit:N=…``, ``HOST:PORT=…``, ``HOST=…``, or a plain name for the
        default); the name after ``=`` is not looked up. Replay uses it to bind
        the profile texts stored in a log (:func:`loads_profile`) as recorded.
        """
        return cls([_rule(spec, _given(profile)) for spec, profile in bound])

    def _add(self, r: _Rule) -> None:
        self._profiles[id(r.profile)] = r.profile
        if r.unit is not None:
            self._units[r.unit] = r.profile
        elif r.host is not None and r.port is not None:
            self._hostports[(r.host, r.port)] = r.profile
        elif r.host is not None:
            self._hosts[r.host] = r.profile
        else:
            self._default = r.profile
        self._cache.clear()

    @property
    def empty(self) -> bool:
        return not self._profiles

    def for_(self, stream: Stream, unit: int) -> Profile | None:
        """The profile for a server endpoint (``stream.server``) and unit id, or ``None``."""
        key = (stream.server, unit)
        try:
            return self._cache[key]
        except KeyError:
            pass
        found = self._units.get(unit)
        if found is None:
            host, port = split_endpoint(stream.server)
            if port is not None:
                found = self._hostports.get((host, port))
            if found is None:
                found = self._hosts.get(host) or self._hosts.get(stream.server)
            if found is None:
                found = self._default
        self._cache[key] = found
        return found

    def profiles(self) -> list[Profile]:
        return list(self._profiles.values())

    def sources(self) -> list[tuple[str, str]]:
        """(profile name, TOML text) of every bound profile, so logs can carry them."""
        return [
            (p.name, p.source if p.source is not None else dump_profile(p))
            for p in self._profiles.values()
        ]


def _given(profile: Profile) -> Callable[[str, str], Profile]:
    """The look-up of a profile already loaded: ``profile`` whatever the name."""

    def get(_name: str, _spec: str) -> Profile:
        return profile

    return get


def _rule(spec: str, get: Callable[[str, str], Profile]) -> _Rule:
    """One ``--profile`` spec as a rule; ``get(name, spec)`` gives the profile it names."""
    spec = spec.strip()
    target, eq, name = spec.rpartition("=")
    if not eq:
        return _Rule(spec, get(spec, spec))
    target = target.strip()
    name = name.strip()
    if target.lower().startswith("unit:"):
        num = target[5:].strip()
        if not num.isdigit() or not 0 <= int(num) <= 255:
            raise ProfileError(f"--profile {spec!r}: unit must be 0..255, got {num!r}")
        return _Rule(spec, get(name, spec), unit=int(num))
    if target:
        host, port = split_endpoint(target)
        if not host:
            raise ProfileError(f"--profile {spec!r}: empty host")
        if port is not None and not 0 < port < 65536:
            raise ProfileError(f"--profile {spec!r}: port must be 1..65535")
        return _Rule(spec, get(name, spec), host=host, port=port)
    raise ProfileError(f"--profile {spec!r}: nothing before '='")
