"""``mbmon demo``'s log file: which ``-w`` it accepts, and whether an existing file is
the log of an earlier demo (the only kind of file a demo overwrites)."""

from __future__ import annotations

import struct
from pathlib import Path

#: ``source`` of a demo log's metadata; a log whose source starts so may be overwritten.
SOURCE_PREFIX = "mbmon demo"

_MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_demo_log(path: Path) -> bool:
    """Whether ``path`` is an MCAP log an earlier ``mbmon demo`` wrote (so it may be overwritten).

    The file must start with the MCAP magic and a header written by mbmon, and
    its ``mbmon`` metadata must name the demo as its source.
    """
    try:
        with path.open("rb") as f:
            head = f.read(64)
    except OSError:
        return False
    if not head.startswith(_MCAP_MAGIC) or len(head) < 8 + 9 + 4:
        return False
    if head[8] != 0x01:  # the Header record
        return False
    pos = 8 + 9
    (n,) = struct.unpack_from("<I", head, pos)  # profile
    pos += 4 + n
    if pos + 4 > len(head):
        return False
    (n,) = struct.unpack_from("<I", head, pos)  # library
    if not head[pos + 4 : pos + 4 + n].startswith(b"mbmon"):
        return False
    from mbmon.io.mcap.layout import METADATA_NAME
    from mbmon.io.mcap.reader import LogError, McapLog

    try:
        with McapLog(path) as log:
            source = log.metadata.get(METADATA_NAME, {}).get("source", "")
    except (LogError, OSError, ValueError):
        return False
    return source.startswith(SOURCE_PREFIX)


def check_log_path(text: str) -> Path:
    """The ``-w`` path, or a :class:`UsageError` when it is not a .mcap name or would
    overwrite anything but an earlier demo's log."""
    from mbmon.commands.common import UsageError

    path = Path(text)
    if path.suffix.lower() != ".mcap":
        raise UsageError(
            f"{text}: the demo writes an MCAP log: use a name ending in .mcap "
            "(mbmon export converts it to .csv, .jsonl, .txt or .pcap afterwards)"
        )
    if path.is_dir():
        raise UsageError(f"{text}: is a directory")
    if path.exists() and not is_demo_log(path):
        raise UsageError(
            f"{text}: exists and is not the log of an earlier demo; refusing to overwrite "
            "it (choose another name with -w)"
        )
    return path
