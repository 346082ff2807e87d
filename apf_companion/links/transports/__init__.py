"""MAVLink transports, one class per endpoint kind, looked up in ``TRANSPORTS`` (no ``if kind is ...`` chains).

=================  ============  ===========================================================
kind               class         receives / sends
=================  ============  ===========================================================
``udpin``          ``UdpIn``     any peer / every peer heard from (at most ``MAX_UDP_PEERS``)
``udpout``         ``UdpOut``    its one address
``tcp``            ``TcpClient`` its server; reconnects with backoff
``tcpin``          ``TcpServer`` every client; one named task per client
``serial``         ``SerialPort`` the device
=================  ============  ===========================================================
"""

from __future__ import annotations

from collections.abc import Mapping

from apf_companion.links.endpoint import EndpointKind
from apf_companion.links.transports.base import MAX_WRITE_BUFFER_B, Transport, TransportFactory
from apf_companion.links.transports.serialport import SerialPort
from apf_companion.links.transports.tcp import TCP_BACKOFF_MAX_S, TCP_BACKOFF_MIN_S, TcpClient, TcpServer
from apf_companion.links.transports.udp import MAX_UDP_PEERS, UdpIn, UdpOut

__all__ = [
    "MAX_UDP_PEERS",
    "MAX_WRITE_BUFFER_B",
    "TCP_BACKOFF_MAX_S",
    "TCP_BACKOFF_MIN_S",
    "TRANSPORTS",
    "SerialPort",
    "TcpClient",
    "TcpServer",
    "Transport",
    "TransportFactory",
    "UdpIn",
    "UdpOut",
]

TRANSPORTS: Mapping[EndpointKind, TransportFactory] = {
    EndpointKind.UDPIN: UdpIn,
    EndpointKind.UDPOUT: UdpOut,
    EndpointKind.TCP: TcpClient,
    EndpointKind.TCPIN: TcpServer,
    EndpointKind.SERIAL: SerialPort,
}
