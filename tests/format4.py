"""Log format 4 in tests: a log's messages with the /modbus/raw messages it left out put
back (rebuilt from their frames' ``chunk`` marker, as every reader does) and the marker
taken off: what a live feed serves and what a format-3 log holds of the same items."""

from __future__ import annotations

from mbmon.io.mcap.layout import CHUNK_MARKS, TOPIC_FRAMES, TOPIC_RAW, frame_chunk
from mbmon.io.mcap.proto import decode_frame, encode_raw

MARKS = frozenset(CHUNK_MARKS.values())


def as_format3(messages: list[tuple[str, int, bytes]]) -> list[tuple[str, int, bytes]]:
    """``(topic, log_time, data)`` messages of a format-4 log as format 3 writes them: a
    frame message ending with a marker gets its chunk's raw message back in front of it
    (made with the pure encoder from the frame's own fields) and loses the marker."""
    out: list[tuple[str, int, bytes]] = []
    for topic, log_time, data in messages:
        if topic == TOPIC_FRAMES and data[-6:] in MARKS:
            chunk = frame_chunk(decode_frame(data))
            assert chunk is not None
            out.append((TOPIC_RAW, log_time, encode_raw(chunk)))
            data = data[:-6]
        out.append((topic, log_time, data))
    return out


def left_out(messages: list[tuple[str, int, bytes]]) -> int:
    """How many chunks a log's messages left out (frames messages with the marker)."""
    return sum(1 for topic, _, data in messages if topic == TOPIC_FRAMES and data[-6:] in MARKS)
