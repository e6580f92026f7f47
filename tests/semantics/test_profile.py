"""Profile loader, look-up, TOML round trip and --profile binding."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from mbmon.model import Stream, Transport
from mbmon.semantics.profile import (
    Profile,
    ProfileBinding,
    ProfileError,
    builtin_profile_text,
    dump_profile,
    load_profile,
    loads_profile,
)

USER = textwrap.dedent(
    """\
    [profile]
    name = "cell"
    description = "a user profile"

    [[channels]]
    name = "Channel 1"
    coils = [0, 7]

    [[notes]]
    title = "why"
    text = "because"

    [[coils]]
    name = "Q{n}"
    address = 16
    n = [1, 8]
    labels = { 1 = "Clamp", 8 = "Horn" }

    [[holding_registers]]
    name = "R10"
    address = 10
    type = "u16"
    label = "mode"
    range = [0, 3]
    enum = { 0 = "off", 1 = "auto", "-1" = "fault" }

    [[holding_registers]]
    name = "flow"
    address = 20
    type = "f32"
    word_order = "high_low"
    unit = "l/min"

    [[holding_registers]]
    name = "T{n}"
    address = 100
    n = [0, 3]
    stride = 3
    type = "i32"
    scale = 0.1
    unit = "°C"
    display = "dec"

    [[holding_registers]]
    name = "Slot[{n}]"
    address = 200
    n = [1, 4]
    stride = 6
    select = "kind"

    [[holding_registers.fields]]
    name = "kind"
    offset = 0
    type = "u16"
    enum = { 1 = "round", 2 = "square" }

    [[holding_registers.fields]]
    name = "Size"
    offset = 1
    type = "u32"
    scale = 0.01
    variants = { 1 = { name = "D", unit = "mm" }, 2 = { name = "Edge", unit = "mm", scale = 0.1 } }

    [[input_registers]]
    name = "ver"
    address = 50
    type = "version"
    words = 3
    format = "v{0}.{1}-{2}"

    [[input_registers]]
    name = "dump"
    address = 60
    type = "block"
    words = 10
    """
)


def test_builtin_profiles_load() -> None:
    hrss = load_profile("hrss")
    assert hrss.name == "hrss" and hrss.session == "hrss"
    assert len(hrss.channels) == 2 and hrss.notes
    xeg = load_profile("xeg")
    assert xeg.name == "xeg" and xeg.session is None


@pytest.mark.parametrize(
    ("table", "address", "name", "label", "base"),
    [
        ("coils", 0, "SI1", "Start", 0),
        ("coils", 7, "SI8", "RSR4", 7),
        ("coils", 8, "SI9", None, 8),
        ("coils", 255, "SI256", None, 255),
        ("coils", 300, "DO[1]", None, 300),
        ("coils", 302, "DO[3]", None, 302),
        ("coils", 555, "DO[256]", None, 555),
        ("discrete_inputs", 0, "SO1", "Run", 0),  # Table 45, not Table 12
        ("discrete_inputs", 3, "SO4", "Ready", 3),
        ("discrete_inputs", 307, "DI[8]", None, 307),
        ("input_registers", 0, "SRW[1]", None, 0),
        ("input_registers", 31, "SRW[32]", None, 31),
        ("input_registers", 301, "A1", None, 300),
        ("input_registers", 411, "C", None, 410),
        ("input_registers", 503, "IR502", "HRSS error", 502),
        ("input_registers", 524, "IR524", "motion state", 524),
        ("input_registers", 251, "returns", "command returns", 202),
        ("holding_registers", 201, "R201", None, 201),
        ("holding_registers", 226, "params", "parameters", 202),
        ("holding_registers", 300, "Timer[1]", None, 300),  # 298 + 2n
        ("holding_registers", 305, "Timer[3]", None, 304),
        ("holding_registers", 339, "Timer[20]", None, 338),
        ("holding_registers", 401, "Counter[1]", None, 400),  # 398 + 2n
        ("holding_registers", 1000, "PR[1].type", None, 1000),
        ("holding_registers", 1019, "PR[2].type", None, 1019),  # 1000 + 19(n-1)
        ("holding_registers", 1021, "PR[2].Value1", None, 1020),
        ("holding_registers", 1037, "PR[2].Value9", None, 1036),
        ("holding_registers", 1949, "PR[50].Value9", None, 1948),
    ],
)
def test_hrss_lookup(table: str, address: int, name: str, label: str | None, base: int) -> None:
    ref = load_profile("hrss").lookup(table, address)
    assert ref is not None
    assert (ref.name, ref.label, ref.address) == (name, label, base)
    # second ask is the memoised answer
    assert load_profile("hrss").lookup(table, address) == ref


@pytest.mark.parametrize(
    ("table", "address"),
    [
        ("coils", 256),
        ("coils", 299),
        ("coils", 556),
        ("discrete_inputs", 299),
        ("input_registers", 99),
        ("input_registers", 312),
        ("input_registers", 504),
        ("holding_registers", 340),
        ("holding_registers", 999),
        ("holding_registers", 1950),
        ("nonsense", 0),
    ],
)
def test_hrss_lookup_gaps(table: str, address: int) -> None:
    assert load_profile("hrss").lookup(table, address) is None


def test_hrss_enums_match_table_16() -> None:
    p = load_profile("hrss")
    r201 = p.lookup("holding_registers", 201)
    ir201 = p.lookup("input_registers", 201)
    assert r201 is not None and ir201 is not None
    assert r201.field.enum == ir201.field.enum
    assert r201.field.enum is not None
    assert r201.field.enum[0] == "PTP" and r201.field.enum[1] == "LIN"
    assert r201.field.enum[6] == "Motion Stop" and r201.field.enum[100] == "Set PR"
    assert r201.field.enum[205] == "Get Home Position"
    assert len(r201.field.enum) == 19


def test_hrss_channels() -> None:
    p = load_profile("hrss")
    ch1 = p.channel_of("coils", 127)
    ch2 = p.channel_of("coils", 128)
    assert ch1 is not None and ch1.name == "Channel 1"
    assert ch2 is not None and ch2.name == "Channel 2"
    assert p.channel_of("holding_registers", 14) is ch1
    assert p.channel_of("holding_registers", 15) is ch2
    assert p.channel_of("holding_registers", 200) is None


def test_xeg_lookup() -> None:
    p = load_profile("xeg")
    ref = p.lookup("input_registers", 773)
    assert ref is not None and ref.name == "IR771" and ref.address == 771 and ref.words == 4
    assert p.lookup("input_registers", 775) is None
    model = p.lookup("holding_registers", 1536)
    assert model is not None and model.field.enum is not None
    assert model.field.enum[2624] == "XEG-64"


def test_user_profile_round_trip(tmp_path: Path) -> None:
    p = loads_profile(USER, file="cell.toml")
    text = dump_profile(p)
    q = loads_profile(text)
    assert q == p
    # and through a file
    f = tmp_path / "cell.toml"
    f.write_text(text, "utf-8")
    r = load_profile(f)
    assert r == p and r.path == str(f)
    # a change is seen by ==
    assert loads_profile(USER.replace('"Horn"', '"Bell"')) != p


@pytest.mark.parametrize("name", ["hrss", "xeg"])
def test_builtin_round_trip(name: str) -> None:
    p = load_profile(name)
    assert loads_profile(dump_profile(p)) == p


def test_user_profile_lookup() -> None:
    p = loads_profile(USER)
    assert p.lookup("coils", 16) is not None
    ref = p.lookup("coils", 16)
    assert ref is not None and (ref.name, ref.label) == ("Q1", "Clamp")
    t = p.lookup("holding_registers", 104)  # T1 at 100 + 3*1, two words
    assert t is not None and t.name == "T1" and t.address == 103
    assert p.lookup("holding_registers", 105) is None  # stride gap
    s = p.lookup("holding_registers", 208)  # Slot[2] at 206: Size at +1..+2
    assert s is not None and s.name == "Slot[2].Size" and s.address == 207
    mode = p.lookup("holding_registers", 10)
    assert mode is not None and mode.field.enum == {0: "off", 1: "auto", -1: "fault"}


def _error(text: str, file: str = "my.toml") -> ProfileError:
    with pytest.raises(ProfileError) as info:
        loads_profile(text, file=file)
    return info.value


def test_error_bad_scale_names_file_line_key() -> None:
    bad = USER.replace("scale = 0.1", 'scale = "x"')
    err = _error(bad)
    line = bad.splitlines().index('scale = "x"') + 1
    assert err.file == "my.toml"
    assert err.line == line
    assert err.key == "holding_registers[2].scale"
    assert str(err) == (f'my.toml:{line}: holding_registers[2] "scale": expected a number, got "x"')


def test_error_in_sub_field() -> None:
    bad = USER.replace("offset = 1", "offset = -1")
    err = _error(bad)
    assert err.key == "holding_registers[3].fields[1].offset"
    assert err.line == bad.splitlines().index("offset = -1") + 1
    assert "outside 0..65535" in str(err)


def test_error_syntax_has_line() -> None:
    bad = USER.replace('type = "u16"\nlabel = "mode"', 'type = "u16\nlabel = "mode"')
    err = _error(bad)
    assert err.line == bad.splitlines().index('type = "u16') + 1
    assert str(err).startswith(f"my.toml:{err.line}: TOML syntax")


@pytest.mark.parametrize(
    ("change", "key", "reason"),
    [
        (('type = "f32"', 'type = "float"'), "holding_registers[1].type", "expected one of"),
        (
            ('name = "R10"\n', 'name = "R10"\ncolour = 3\n'),
            "holding_registers[0].colour",
            "unknown key",
        ),
        (("range = [0, 3]", "range = [3, 0]"), "holding_registers[0].range", "above high"),
        (('"-1" = "fault"', 'x = "fault"'), "holding_registers[0].enum", "not an integer"),
        (('name = "T{n}"', 'name = "T"'), "holding_registers[2].name", "{n}"),
        (("address = 100", "address = 9"), "holding_registers[2].address", "overlaps"),
        (('select = "kind"', 'select = "sort"'), "holding_registers[3].select", "no sub-field"),
        (("words = 3", "words = 0"), "input_registers[0].words", "outside 1..125"),
        (
            ('format = "v{0}.{1}-{2}"', 'format = "v{0}.{5}"'),
            "input_registers[0].format",
            "bad format",
        ),
        (
            ('labels = { 1 = "Clamp", 8 = "Horn" }', 'labels = { 9 = "x" }'),
            "coils[0].labels",
            "outside 1..8",
        ),
        (('name = "cell"', "name = 5"), "profile.name", "expected a string"),
        (
            ('description = "a user profile"', "functions = [3, 200]"),
            "profile.functions",
            "function code 200 is outside 1..127",
        ),
        (
            ('description = "a user profile"', "functions = [3, 4, 3]"),
            "profile.functions",
            "listed twice",
        ),
        (('description = "a user profile"', "functions = 3"), "profile.functions", "an array"),
        (('description = "a user profile"', 'functions = ["3"]'), "profile.functions", "integer"),
        (
            ('description = "a user profile"', 'session = "plc"'),
            "profile.session",
            "unknown session 'plc' (known: hrss",
        ),
        (
            (
                '[[coils]]\nname = "Q{n}"\naddress = 16',
                '[[coils]]\nname = "Q{n}"\naddress = 16\ntype = "u16"',
            ),
            "coils[0].type",
            "expected one of bit",
        ),
    ],
)
def test_errors(change: tuple[str, str], key: str, reason: str) -> None:
    assert change[0] in USER
    err = _error(USER.replace(change[0], change[1], 1))
    assert err.key == key
    assert reason in str(err)
    assert str(err).startswith("my.toml")


def test_the_functions_a_device_serves() -> None:
    # HRSS lists them (Table 10); a profile that does not say has none
    assert load_profile("hrss").functions == (1, 2, 3, 4, 5, 6, 15, 16)
    assert load_profile("xeg").functions is None and loads_profile(USER).functions is None
    p = loads_profile(USER.replace('description = "a user profile"', "functions = [3, 0x10]"))
    assert p.functions == (3, 16)
    assert "functions = [3, 16]" in dump_profile(p) and loads_profile(dump_profile(p)) == p


def test_missing_header() -> None:
    err = _error('[[coils]]\nname = "x"\naddress = 0\n')
    assert err.key == "profile" and "missing [profile]" in str(err)


def test_missing_file_and_unknown_name(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match="no such profile file"):
        load_profile(tmp_path / "absent.toml")
    with pytest.raises(ProfileError, match="built-in"):
        load_profile("robotx")


# ---------------------------------------------------------------------- binding


def _stream(server: str) -> Stream:
    return Stream(0, Transport.TCP, "10.0.0.9:40000", server)


def test_binding_precedence(tmp_path: Path) -> None:
    f = tmp_path / "cell.toml"
    f.write_text(USER, "utf-8")
    b = ProfileBinding.parse(
        ["hrss", f"10.0.0.5={f}", "10.0.0.5:1502=xeg", "unit:7=xeg", "[fe80::1]:502=xeg"]
    )
    name = lambda s, u: p.name if (p := b.for_(_stream(s), u)) else None  # noqa: E731
    assert name("10.0.0.1:502", 1) == "hrss"  # default
    assert name("10.0.0.5:502", 1) == "cell"  # host
    assert name("10.0.0.5:1502", 1) == "xeg"  # host:port beats host
    assert name("10.0.0.1:502", 7) == "xeg"  # unit beats default
    assert name("10.0.0.5:502", 7) == "xeg"  # unit beats host
    assert name("[fe80::1]:502", 1) == "xeg"
    assert name("[fe80::1]:503", 1) == "hrss"
    assert {n for n, _ in b.sources()} == {"hrss", "cell", "xeg"}
    assert dict(b.sources())["cell"] == USER
    assert len(b.profiles()) == 3  # "xeg" loaded once for three rules


def test_binding_without_default() -> None:
    b = ProfileBinding.parse(["unit:3=xeg", "/dev/ttyUSB0=hrss"])
    assert b.for_(_stream("10.0.0.1:502"), 1) is None
    got = b.for_(_stream("10.0.0.1:502"), 3)
    assert got is not None and got.name == "xeg"
    serial = Stream(1, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
    got = b.for_(serial, 1)
    assert got is not None and got.name == "hrss"
    assert ProfileBinding.parse([]).empty and not b.empty


def test_binding_from_loaded_profiles_reads_no_file(tmp_path: Path) -> None:
    """Specs bound to profiles parsed from text: the name after '=' is never looked up."""
    cell = loads_profile(USER, file="stored:cell")
    xeg = loads_profile(builtin_profile_text("xeg"))
    missing = tmp_path / "gone.toml"  # a file that does not exist: must not be read
    b = ProfileBinding.from_profiles(
        [(f"unit:7={missing}", xeg), (f"10.0.0.5={missing}", cell), ("whatever", xeg)]
    )
    name = lambda s, u: p.name if (p := b.for_(_stream(s), u)) else None  # noqa: E731
    assert name("10.0.0.5:502", 1) == "cell"
    assert name("10.0.0.5:502", 7) == "xeg"  # unit beats host, as with parse()
    assert name("10.0.0.1:502", 1) == "xeg"  # the plain spec is the default
    assert dict(b.sources())["cell"] == USER  # the stored text goes on into new logs
    assert len(b.profiles()) == 2
    with pytest.raises(ProfileError, match=r"unit must be 0\.\.255"):
        ProfileBinding.from_profiles([("unit:300=x", cell)])


def test_binding_parse_with_a_loader() -> None:
    asked: list[str] = []

    def loader(name: str) -> Profile:
        asked.append(name)
        return loads_profile(USER, file=name)

    b = ProfileBinding.parse(["unit:1=a", "unit:2=a", "10.0.0.1=b"], loader=loader)
    assert asked == ["a", "b"]  # each distinct name loaded once
    got = b.for_(_stream("10.0.0.9:502"), 2)
    assert got is not None and got.name == "cell"


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("unit:x=hrss", "unit must be 0..255"),
        ("unit:300=hrss", "unit must be 0..255"),
        ("=hrss", "nothing before"),
        ("10.0.0.1=", "no profile name"),
        ("10.0.0.1:0=hrss", "port must be"),
        ("10.0.0.1=nonexistent.toml", "no such profile file"),
    ],
)
def test_binding_errors(spec: str, match: str) -> None:
    with pytest.raises(ProfileError, match=match):
        ProfileBinding.parse([spec])


def test_profile_equality_ignores_source() -> None:
    a = loads_profile(USER)
    b = loads_profile(USER + "\n# a comment\n")
    assert a == b and a.source != b.source
    assert isinstance(a, Profile)


def test_error_in_enum_sub_table_points_at_its_header() -> None:
    from mbmon.semantics.profile import builtin_profile_text

    text = builtin_profile_text("hrss")
    bad = text.replace('2 = "Fail"', 'two = "Fail"', 1)
    err = _error(bad, file="hrss.toml")
    assert err.key == "input_registers[4].enum"
    lines = bad.splitlines()
    assert lines[err.line - 1] == "[input_registers.enum]"  # type: ignore[operator]
    assert lines.index('two = "Fail"') > err.line - 1  # type: ignore[operator]
