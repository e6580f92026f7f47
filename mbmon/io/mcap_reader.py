"""Moved to :mod:`mbmon.io.mcap.reader`; this name stays for code written against it."""

from mbmon.io.mcap.reader import LogAttachment, LogError, LogMessage, McapLog, ReadStatus, open_log

__all__ = ["LogAttachment", "LogError", "LogMessage", "McapLog", "ReadStatus", "open_log"]
