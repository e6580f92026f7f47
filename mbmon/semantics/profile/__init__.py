"""Device register maps as data: the profile model, loader, dumper and ``--profile`` binding.

A profile (``docs/profiles.md``) describes per Modbus data table the fields a
device exposes. The package splits that job along its seams:
:mod:`~.model` (frozen types, field look-up), :mod:`~.load` (TOML text → checked
:class:`Profile`), :mod:`~.dump` (:class:`Profile` → TOML text) and
:mod:`~.binding` (which profile applies to which server endpoint / unit id).
It knows nothing about frames; :mod:`mbmon.semantics.annotate` turns fields
into notes.
"""

from mbmon.semantics.profile.binding import ProfileBinding, split_endpoint
from mbmon.semantics.profile.dump import dump_profile
from mbmon.semantics.profile.load import builtin_profile_text, load_profile, loads_profile
from mbmon.semantics.profile.model import (
    BUILTIN_PROFILES,
    REGISTER_PREFIX,
    TABLES,
    Channel,
    Field,
    FieldRef,
    Note,
    Profile,
    ProfileError,
    Variant,
)

__all__ = [
    "BUILTIN_PROFILES",
    "REGISTER_PREFIX",
    "TABLES",
    "Channel",
    "Field",
    "FieldRef",
    "Note",
    "Profile",
    "ProfileBinding",
    "ProfileError",
    "Variant",
    "builtin_profile_text",
    "dump_profile",
    "load_profile",
    "loads_profile",
    "split_endpoint",
]
