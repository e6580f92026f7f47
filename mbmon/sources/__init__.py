"""mbmon.sources: where bytes come from (files, captures, serial ports, the proxy, logs).

This package's own module holds only what every serial-facing part shares and
the command line needs before any source is imported (it imports nothing).
"""

DEFAULT_BAUD = 115200
"""The one default baud rate of every serial option (sniff, proxy, sim) and of
:class:`mbmon.sources.serial.SerialSettings`: the HIWIN controller's default
line, 115200 8N1 (the Modbus spec's default is 19200 8E1)."""
