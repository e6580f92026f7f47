"""Copying an MCAP log into a new, finished and indexed one (``export -o FILE.mcap``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def copy_log(log: Any, target: Path, flt: Any) -> None:
    """Copy every (recovered) message into a new, finished and indexed MCAP file."""
    from mbmon import __version__
    from mbmon.io.mcap.layout import TOPIC_SCHEMAS, schema_text
    from mbmon.io.mcap.writer import McapFileWriter

    with open(target, "wb") as f:
        writer = McapFileWriter(f)
        writer.start(library=f"mbmon {__version__}")
        channels: dict[str, int] = {}
        for name, data in log.metadata.items():
            writer.add_metadata(name, data)
        for att in log.attachments:
            writer.add_attachment(0, att.log_time, att.name, att.media_type, att.data)

        def channel(topic: str) -> int:
            cid = channels.get(topic)
            if cid is None:
                stored = log.schema_of(topic)
                if stored is not None:  # the messages are copied as stored: so is the schema
                    name, encoding, data = stored
                    message_encoding = "protobuf" if encoding == "protobuf" else "json"
                else:  # none stored: the messages are JSON (format 3 stores its schemas)
                    name = TOPIC_SCHEMAS.get(topic, "")
                    encoding, data = ("jsonschema", schema_text(name)) if name else ("", b"")
                    message_encoding = "json"
                sid = writer.register_schema(name, encoding, data) if name else 0
                cid = writer.register_channel(topic, message_encoding, sid)
                channels[topic] = cid
            return cid

        for topic in TOPIC_SCHEMAS:
            channel(topic)
        try:
            for msg in log.messages():
                ts = msg.log_time / 1e9
                if flt.since is not None and ts < flt.since:
                    continue
                if flt.until is not None and ts > flt.until:
                    continue
                writer.add_message(channel(msg.topic), msg.log_time, msg.raw)
        finally:
            writer.finish()
