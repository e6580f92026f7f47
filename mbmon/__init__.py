"""mbmon: a Modbus RTU/TCP protocol analyzer and monitor for HIWIN robot cells.

``import mbmon`` stays light: it never imports scapy or pyserial (sources are
imported lazily by the commands that need them).
"""

__version__ = "0.1.0"
