"""Writing captures (pcap, pcapng) and the packets in them. Pure Python, no scapy.

- :mod:`~mbmon.io.pcap.packets`: link-layer, IP, TCP and UDP bytes for every link type
  the reader dissects, and :class:`TcpConversation` (consistent sequence numbers);
- :mod:`~mbmon.io.pcap.files`: the pcap and pcapng file layouts (:class:`PcapWriter`,
  :class:`PcapngWriter`);
- :mod:`~mbmon.io.pcap.chunks`: chunks and events back into a capture
  (:class:`ChunkWriter`, the one writer behind ``-w x.pcap`` and ``export -o x.pcap``).

Reading captures is :mod:`mbmon.sources.pcapfile`; its output read back gives the same
chunks and events.
"""

from mbmon.io.pcap.chunks import (
    ChunkWriter,
)
from mbmon.io.pcap.files import (
    PcapngWriter,
    PcapWriter,
)
from mbmon.io.pcap.packets import (
    ACK,
    ETHERTYPE_IPV4,
    ETHERTYPE_IPV6,
    ETHERTYPE_QINQ,
    ETHERTYPE_VLAN,
    FIN,
    LINKTYPE_ETHERNET,
    LINKTYPE_IPV4,
    LINKTYPE_IPV6,
    LINKTYPE_LINUX_SLL,
    LINKTYPE_LINUX_SLL2,
    LINKTYPE_LOOP,
    LINKTYPE_NULL,
    LINKTYPE_RAW,
    LINKTYPE_USER0,
    MODBUS_PORT,
    PSH,
    RST,
    SYN,
    TcpConversation,
    ethernet_frame,
    ip_packet,
    ipv4_packet,
    ipv6_packet,
    join_endpoint,
    link_frame,
    mac_for,
    parse_endpoint,
    tcp_frame,
    tcp_header,
    udp_frame,
    udp_header,
)

__all__ = [
    "ACK",
    "ETHERTYPE_IPV4",
    "ETHERTYPE_IPV6",
    "ETHERTYPE_QINQ",
    "ETHERTYPE_VLAN",
    "FIN",
    "LINKTYPE_ETHERNET",
    "LINKTYPE_IPV4",
    "LINKTYPE_IPV6",
    "LINKTYPE_LINUX_SLL",
    "LINKTYPE_LINUX_SLL2",
    "LINKTYPE_LOOP",
    "LINKTYPE_NULL",
    "LINKTYPE_RAW",
    "LINKTYPE_USER0",
    "MODBUS_PORT",
    "PSH",
    "RST",
    "SYN",
    "ChunkWriter",
    "PcapWriter",
    "PcapngWriter",
    "TcpConversation",
    "ethernet_frame",
    "ip_packet",
    "ipv4_packet",
    "ipv6_packet",
    "join_endpoint",
    "link_frame",
    "mac_for",
    "parse_endpoint",
    "tcp_frame",
    "tcp_header",
    "udp_frame",
    "udp_header",
]
